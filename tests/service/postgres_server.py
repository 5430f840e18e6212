"""A real PostgreSQL server for the tests: initdb in a fresh folder, a free port on 127.0.0.1,
its unix socket in the same folder, one database per test. PostgreSQL refuses to run as
root, so as root the server runs as the `postgres` user (Debian's package makes it) or
`nobody`, owning the folder. Binaries: Debian's /usr/lib/postgresql/N/bin (see
scripts/ensure-postgres.sh), else whatever `pg_ctl` is on PATH."""
from __future__ import annotations

import os
import pwd
import re
import shutil
import subprocess
import tempfile
import time
import uuid
from pathlib import Path

import psycopg

from service_harness import free_port

SUPERUSER = "renderloop"  # the role initdb makes; trust auth, the server is reachable only from here
START_SECONDS = 60


def find_bin_dir() -> Path | None:
    """The newest Debian cluster binaries, else the folder of `pg_ctl` on PATH; None if neither."""
    debian = sorted(Path("/usr/lib/postgresql").glob("*/bin/pg_ctl"),
                    key=lambda p: int(re.sub(r"\D", "", p.parent.parent.name) or 0))
    if debian:
        return debian[-1].parent
    on_path = shutil.which("pg_ctl")
    return Path(on_path).parent if on_path else None


def server_account() -> pwd.struct_passwd | None:
    """The unprivileged account to run the server as; None when we are not root."""
    if os.geteuid() != 0:
        return None
    for name in ("postgres", "nobody"):
        try:
            return pwd.getpwnam(name)
        except KeyError:
            continue
    raise RuntimeError("running as root and neither a 'postgres' nor a 'nobody' account exists")


class PostgresServer:
    def __init__(self, bin_dir: Path) -> None:
        self.bin_dir = bin_dir
        self.account = server_account()
        # Not under pytest's tmp folder: that is private to root, and the server's user must
        # reach its data folder.
        self.root = Path(tempfile.mkdtemp(prefix="renderloop-pg-"))
        self.data = self.root / "data"
        self.port = free_port()

    def _run(self, *args: str) -> None:
        user = {"user": self.account.pw_uid, "group": self.account.pw_gid, "extra_groups": []} if self.account else {}
        result = subprocess.run([str(self.bin_dir / args[0]), *args[1:]], cwd=self.root, capture_output=True,
                                text=True, timeout=START_SECONDS, **user)
        if result.returncode != 0:
            raise RuntimeError(f"{' '.join(args)} failed ({result.returncode}):\n{result.stdout}{result.stderr}"
                               f"\n{self.log()}")

    def log(self) -> str:
        log = self.root / "server.log"
        return log.read_text(errors="replace") if log.exists() else ""

    def start(self) -> "PostgresServer":
        if self.account:
            os.chown(self.root, self.account.pw_uid, self.account.pw_gid)
        # fsync off: a test database need not survive a power cut, and it makes initdb fast.
        self._run("initdb", "-D", str(self.data), "-U", SUPERUSER, "--auth=trust", "-E", "UTF8", "--no-sync")
        options = (f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 -c fsync=off "
                   "-c synchronous_commit=off -c full_page_writes=off")
        self._run("pg_ctl", "-D", str(self.data), "-l", str(self.root / "server.log"), "-o", options, "-w",
                  "-t", str(START_SECONDS), "start")
        return self

    def stop(self) -> None:
        try:
            self._run("pg_ctl", "-D", str(self.data), "-m", "immediate", "-w", "stop")
        finally:
            shutil.rmtree(self.root, ignore_errors=True)

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://{SUPERUSER}@127.0.0.1:{self.port}/{database}"

    def new_database(self) -> str:
        """A fresh, empty database; its URL."""
        name = f"test_{uuid.uuid4().hex[:16]}"
        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f"CREATE DATABASE {name}")
        return self.url(name)

    def drop_connections(self, database_url: str) -> int:
        """Ends every client connection to that database from the server side (what a server
        restart does to them) and waits until they are gone; how many there were."""
        name = database_url.rsplit("/", 1)[1]
        with psycopg.connect(self.url(), autocommit=True) as conn:
            others = "SELECT pid FROM pg_stat_activity WHERE datname = %s AND pid <> pg_backend_pid()"
            pids = [row[0] for row in conn.execute(others, (name,)).fetchall()]
            for pid in pids:
                conn.execute("SELECT pg_terminate_backend(%s)", (pid,))
            deadline = time.monotonic() + START_SECONDS
            while conn.execute(others, (name,)).fetchall() and time.monotonic() < deadline:
                time.sleep(0.05)
        return len(pids)
