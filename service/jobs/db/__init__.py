"""Where job records live: the SQLite file in the data dir (default) or a PostgreSQL server
(`serve --db postgresql://…`). Each backend only connects, runs one statement at a time,
and migrates the schema; the store's logic is written once in service/jobs/store.py."""
