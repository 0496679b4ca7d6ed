"""IPC-CFX (IPC-2591) for the line (docs/cfx.md): the station's work, tests and state as CFX messages
over AMQP 1.0, through the durable outbox.

    messages.py  the pure builder: stored records in, CFX envelopes (typed dicts) out
    amqp.py      the AMQP 1.0 sender (python-qpid-proton, blocking API, one thread)
    outbox.py    the worker the daemon runs: queue messages from the database, send them in order
"""
