"""lodcast.service: the HTTP API, batch jobs, the client and the service's CLI commands. Nothing is imported here,
so that `import lodcast` stays cheap.

- settings.py  Settings (LODCAST_* environment: root, token, queue, caps, concurrency, heartbeat)
- app.py       create_app(settings) -> FastAPI: the routes and their errors
- asgi.py      the request-body limit (middleware) and the offline Swagger UI
- models.py    response bodies and documented errors (the OpenAPI schema's types; the client's results)
- volumes.py   volume ids, path-traversal and symlink safety under the store root
- rendering.py scene validation against the caps, the per-process render engine, encoding
- jobs.py      job kinds (turntable, scenes, tf_sweep, volumes, ingest), their frames, atomic frame files, GIF/MP4
- records.py   job records beside the queue (SQLite table / Redis hashes) with compare-and-set
- queue.py     huey (SqliteHuey / RedisHuey), JobQueue (submit, cancel, reap, run), Worker
- client.py    lodcast.Client and lodcast.AsyncClient over httpx
- commands.py  `lodcast serve | worker | submit | jobs`
- testing.py   helpers for tests, the benchmark and the smoke script (tiny volume, redis-server, processes)
"""
