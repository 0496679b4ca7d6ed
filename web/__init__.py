"""Web: FastAPI REST API, server-sent events, operator page and MES outbox (create_app in web.app)."""

__version__ = "0.1.0"
