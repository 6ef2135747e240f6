"""rayfarm's worker side: the Celery app and the task that runs a work unit.

Workers are stateless compute. They talk to the broker (Redis) only: scenes
and a DAG unit's inputs arrive by content hash, partial films leave the same
way (published under their SHA-256; the task's result names the digest), and
a heartbeat key says "still rendering". They never touch the job database.
"""
