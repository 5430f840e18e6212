"""The Ray wall: a `renderloop serve` on the Ray backend (a real local Ray runtime) listens only
on loopback — every process it started, GCS, raylet, agents, workers included — runs Ray with
token auth (the token file 0600, never ~/.ray/auth_token), keeps its own secrets out of the Ray
processes, and refuses to join a cluster without token auth unless told --insecure-ray. The same
server (two Ray workers, one Ray start for the module) runs two submitted jobs at once."""
from __future__ import annotations

import os
import stat
import time
from pathlib import Path

import httpx
import pytest

from process_sockets import listeners, process_tree
from service_harness import Server, finished, renderloop_cli, wait_for

pytestmark = pytest.mark.requires("ray")

SECRET = "s3cret-token-for-the-ray-wall"
DB_SECRET = "postgresql://renderloop:hunter2@db.invalid:5432/jobs"
RAY_STARTUP_SECONDS = 300  # a Ray runtime on a loaded 2-core machine can take minutes
AGENT_ANSWER_SECONDS = 180  # how long the dashboard agent may take to answer on its HTTP port


WORKERS = 2


@pytest.fixture(scope="module")
def ray_server(tmp_path_factory):
    """One Ray-backed server for the module (two workers), with two jobs submitted at once and
    finished (so Ray workers exist); (server, its HOME, the finished jobs' records)."""
    root = tmp_path_factory.mktemp("ray_seal")
    home = root / "home"
    home.mkdir()
    env = {"RENDERLOOP_CONCURRENCY": "", "RENDERLOOP_WORKERS": str(WORKERS), "RENDERLOOP_TOKEN": SECRET,
           "PGPASSWORD": "hunter2", "HOME": str(home), "RAY_AUTH_MODE": "disabled"}
    server = Server(root / "data", root / "server.log", env=env, startup_seconds=RAY_STARTUP_SECONDS).start()
    try:
        headers = {"authorization": f"Bearer {SECRET}"}
        with httpx.Client(base_url=server.url, timeout=60, headers=headers) as client:
            body = {"scene": "cornell-box", "width": 32, "height": 32, "spp_first": 16, "max_iterations": 3}
            ids = [client.post("/jobs", json=body).json()["id"] for _ in range(WORKERS)]
            jobs = [wait_for(client, job_id, finished, timeout=300) for job_id in ids]
        assert [job["state"] for job in jobs] == ["completed"] * WORKERS, server.log()
        yield server, home, jobs
    finally:
        server.stop()


def environ_of(pid: int) -> dict[str, str]:
    try:
        raw = Path(f"/proc/{pid}/environ").read_bytes()
    except OSError:
        return {}
    return dict(item.split("=", 1) for item in raw.decode(errors="replace").split("\0") if "=" in item)


def command_of(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def ray_processes(server: Server) -> list[int]:
    """Ray's processes under the server: its daemons (site-packages/ray/…) and workers (ray::…)."""
    return [pid for pid in process_tree(server.process.pid)
            if pid != server.process.pid and ("/ray/" in command_of(pid) or command_of(pid).startswith("ray::"))]


def test_serve_with_two_ray_workers_runs_two_submitted_jobs_at_once(ray_server):
    _, _, (a, b) = ray_server
    assert a["started_at"] < b["finished_at"] and b["started_at"] < a["finished_at"]


def test_every_port_of_a_ray_backed_server_listens_on_loopback_only(ray_server):
    server, _, _ = ray_server
    found = listeners(server.process.pid)
    ray_ports = [listener for listener in found if listener.pid != server.process.pid]
    # GCS, raylet (node manager, object manager), agents, a worker: the test sees Ray's ports.
    assert len(ray_ports) >= 5, f"expected Ray's listening sockets in the server's process tree: {found}"
    exposed = [listener for listener in found if not listener.loopback]
    assert not exposed, "listening beyond loopback:\n" + "\n".join(map(str, exposed))


def test_ray_processes_inherit_none_of_the_service_secrets(ray_server):
    server, _, _ = ray_server
    assert environ_of(server.process.pid).get("RENDERLOOP_TOKEN") == SECRET  # the test reads environments
    pids = ray_processes(server)
    assert pids, "no Ray processes under the server"
    for pid in pids:
        environ = environ_of(pid)
        leaked = {name for name in ("RENDERLOOP_TOKEN", "PGPASSWORD") if name in environ}
        assert not leaked, f"process {pid} ({command_of(pid)[:80]}) has {leaked}"
        assert SECRET not in "\0".join(environ.values())


def test_local_ray_runs_with_token_auth_from_a_private_token_file(ray_server):
    server, home, _ = ray_server
    # Ray's agents are started by the raylet with an environment of its making (seen with and
    # without RAY_AUTH_MODE); their refusal is pinned by the dashboard-agent test below.
    pids = [pid for pid in ray_processes(server) if "Agent" not in command_of(pid)]
    environs = [environ_of(pid) for pid in pids]
    modes = {environ.get("RAY_AUTH_MODE") for environ in environs if environ}
    assert modes == {"token"}, (f"RAY_AUTH_MODE in Ray's processes: {modes} (the server was given 'disabled'): "
                                + "; ".join(f"{environ.get('RAY_AUTH_MODE')} {command_of(pid)[:100]}"
                                            for pid, environ in zip(pids, environs)))
    # Ray's agents get the token from the raylet, not the path; the others read the file.
    paths = {environ["RAY_AUTH_TOKEN_PATH"] for environ in environs if "RAY_AUTH_TOKEN_PATH" in environ}
    assert len(paths) == 1, paths
    token = Path(paths.pop())
    assert stat.S_IMODE(token.stat().st_mode) == 0o600
    assert stat.S_IMODE(token.parent.stat().st_mode) == 0o700
    assert not (home / ".ray" / "auth_token").exists(), "Ray wrote its world-readable default token file"


def test_ray_dashboard_agent_refuses_a_request_without_the_token(ray_server):
    server, _, _ = ray_server
    answers: list[int] = []
    # The agent opens its HTTP port some time after the raylet, and on a loaded 2-core machine a
    # request can time out: ask every agent port again until one answers (or the deadline passes).
    deadline = time.monotonic() + AGENT_ANSWER_SECONDS
    while not {401, 403} & set(answers) and time.monotonic() < deadline:
        agents = [listener for listener in listeners(server.process.pid) if "DashboardAgent" in listener.command]
        assert agents, "no dashboard agent found"
        for listener in agents:
            try:
                answers.append(httpx.post(f"http://127.0.0.1:{listener.port}/api/job_agent/jobs/",
                                          json={"entrypoint": "touch /tmp/pwned-by-ray"}, timeout=30).status_code)
            except httpx.HTTPError:
                continue  # a gRPC port, or a port not answering yet
        if not {401, 403} & set(answers):
            time.sleep(2)
    # The job agent's port answers 401; any other HTTP port of the agent must not run the job either.
    assert {401, 403} & set(answers) and not any(200 <= code < 300 for code in answers), answers


def test_serve_refuses_to_join_a_ray_cluster_without_token_auth_unless_insecure_ray(tmp_path):
    env = {"RAY_AUTH_MODE": "disabled", "HOME": str(tmp_path)}
    refused = renderloop_cli("serve", "--ray-address", "127.0.0.1:1", "--data-dir", str(tmp_path / "data"), env=env)
    assert refused.returncode == 2, refused.stderr
    assert "token auth" in refused.stderr and "--insecure-ray" in refused.stderr
    token = tmp_path / "token"
    token.write_text("abc")
    token.chmod(0o644)
    readable = renderloop_cli("serve", "--ray-address", "127.0.0.1:1", "--data-dir", str(tmp_path / "data"),
                              env={**env, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN_PATH": str(token)})
    assert readable.returncode == 2 and "chmod 600" in readable.stderr, readable.stderr
