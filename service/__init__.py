"""rayfarm's service: HTTP API, job ledger, scheduler and the two executors.

`create_app(settings)` (in `service.main`) assembles everything; nothing is
built at import time.
"""
