"""rayfarm's worker side: the Celery app and the task that runs a work unit.

Workers are stateless compute. They talk to the broker (Redis) only: scenes
arrive by content hash, partial films leave through the result backend, and a
heartbeat key says "still rendering". They never touch the job database.
"""
