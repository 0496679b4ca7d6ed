"""REST routes, one module per resource; each route is thin: validate, call the station or the
repository, shape the answer (web/views.py)."""
