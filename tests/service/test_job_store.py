"""The job store on both databases — a real SQLite file in tmp_path and a real PostgreSQL server
(conftest's db_url runs each store test once on each) — and the per-job artifacts folder."""
from __future__ import annotations

import socket
import sqlite3
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import pytest

from service.jobs.artifacts import JobFiles, Preview
from service.jobs.latest import LatestWins
from service.jobs.db.connect import open_database
from service.jobs.db.schema import JOBS, DuplicateKey
from service.jobs.errors import StoreUnavailable
from service.jobs.leases import Leases
from service.jobs.quotas import QuotaExceeded, Quotas
from service.jobs.store import CANCELED, COMPLETED, QUEUED, RUNNING, AlreadySubmitted, JobStore
from service_harness import free_port


@pytest.fixture
def store(tmp_path, db_url):
    s = JobStore(tmp_path, db_url)
    yield s
    s.close()


def test_create_and_read_back(store):
    record = store.create({"scene": "cornell-box", "width": 16}, lambda_value=2.0)
    assert len(record.id) == 32 and record.state == QUEUED
    again = store.get(record.id)
    assert again.spec == {"scene": "cornell-box", "width": 16}
    assert again.lambda_value == 2.0 and again.preview_version == 0
    assert store.job_dir(record.id).is_dir()


def test_the_default_store_is_a_sqlite_file_in_wal_mode(tmp_path):
    JobStore(tmp_path).close()
    journal = sqlite3.connect(tmp_path / "jobs.sqlite").execute("PRAGMA journal_mode").fetchone()[0]
    assert journal == "wal"


def test_a_relative_data_dir_is_held_absolute_so_a_later_chdir_or_a_worker_elsewhere_finds_it(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    store = JobStore("data")
    try:
        assert store.data_dir == tmp_path.resolve() / "data" and store.jobs_dir.is_absolute()
    finally:
        store.close()


def test_a_postgresql_store_keeps_records_in_the_server_and_files_in_the_data_dir(tmp_path, postgres_url):
    store = JobStore(tmp_path / "data", postgres_url)
    job = store.create({}, None)
    assert store.job_dir(job.id) == tmp_path / "data" / "jobs" / job.id and store.job_dir(job.id).is_dir()
    assert not (tmp_path / "data" / "jobs.sqlite").exists()
    store.close()
    other_host = JobStore(tmp_path / "elsewhere", postgres_url)  # a second node sees the same records
    assert other_host.get(job.id).state == QUEUED
    other_host.close()


def test_timestamps_keep_sub_second_precision(store):
    before = time.time()
    job = store.create({}, None)
    store.claim(job.id)
    record = store.get(job.id)
    assert before <= record.created_at <= record.started_at <= time.time()  # a 32-bit float is off by minutes


def test_state_transitions(store):
    job = store.create({}, None)
    assert store.claim(job.id) and not store.claim(job.id)  # only one worker wins
    store.record_iteration(job.id, 2, 32.0, 0.1, {"render": 1.5}, None)
    assert store.bump_preview_version(job.id) == 1
    assert store.bump_preview_version(job.id) == 2
    store.finish(job.id, COMPLETED, stop_reason="max_iterations")
    done = store.get(job.id)
    assert (done.state, done.iteration, done.spp, done.stop_reason) == (COMPLETED, 2, 32.0, "max_iterations")
    assert done.started_at is not None and done.finished_at >= done.started_at
    assert done.timings == {"render": 1.5}


def test_cancel_only_wins_while_queued(store):
    queued, running = store.create({}, None), store.create({}, None)
    store.claim(running.id)
    assert store.cancel_if_queued(queued.id) and store.get(queued.id).state == CANCELED
    assert not store.cancel_if_queued(running.id) and store.get(running.id).state == RUNNING


def test_restart_requeues_running_jobs(tmp_path, db_url):
    first = JobStore(tmp_path, db_url)
    older, job, done = first.create({}, None), first.create({}, None), first.create({}, None)
    for j in (job, older, done):
        first.claim(j.id)
    first.finish(done.id, COMPLETED)
    first.close()  # the process "dies" with two jobs marked running
    second = JobStore(tmp_path, db_url)
    assert second.requeue_running() == [older.id, job.id]  # oldest first, the finished one untouched
    assert second.get(job.id).state == QUEUED and second.ids_in_state(QUEUED) == [older.id, job.id]
    assert second.get(done.id).state == COMPLETED and second.requeue_running() == []
    second.close()


def test_two_servers_racing_to_claim_and_cancel_give_each_job_exactly_one_winner(tmp_path, db_url):
    """Two stores are two server processes' connections; claims and cancels run in threads."""
    stores = [JobStore(tmp_path, db_url) for _ in range(2)]
    jobs = [stores[0].create({}, None).id for _ in range(20)]

    def attempt(store: JobStore, action: str, job: str) -> tuple[str, str] | None:
        won = store.claim(job) if action == "claim" else store.cancel_if_queued(job)
        return (job, action) if won else None

    attempts = [(store, action, job) for job in jobs for store in stores for action in ("claim", "cancel") * 2]
    with ThreadPoolExecutor(8) as pool:
        winners = [w for w in pool.map(lambda a: attempt(*a), attempts) if w]
    assert sorted(job for job, _ in winners) == sorted(jobs)  # one winner per job, never two
    for job, action in winners:
        assert stores[1].get(job).state == (RUNNING if action == "claim" else CANCELED)
    for s in stores:
        s.close()


def test_concurrent_preview_bumps_from_two_servers_each_get_their_own_version(tmp_path, db_url):
    stores = [JobStore(tmp_path, db_url) for _ in range(2)]
    job = stores[0].create({}, None).id
    with ThreadPoolExecutor(8) as pool:
        versions = list(pool.map(lambda i: stores[i % 2].bump_preview_version(job), range(40)))
    assert sorted(versions) == list(range(1, 41)) and stores[1].get(job).preview_version == 40
    for s in stores:
        s.close()


def test_a_database_made_before_the_effects_column_is_migrated(tmp_path, db_url):
    first_release = replace(JOBS, columns=tuple(c for c in JOBS.columns if c.name != "effects"), added=())
    old = open_database(tmp_path, db_url)
    old.ensure_schema(first_release)
    old.execute("INSERT INTO jobs (id, state, spec, created_at) VALUES (?, ?, ?, ?)", ("old", QUEUED, "{}", 1.0))
    old.close()
    store = JobStore(tmp_path, db_url)
    assert store.get("old").effects is None
    store.set_effects("old", {"integrator": "path"})
    assert store.get("old").effects == {"integrator": "path"}
    store.close()


def test_a_list_offset_past_every_row_is_empty(store):
    store.create({}, None)
    assert store.list(offset=2**62) == [] and store.list(offset=1) == []


def test_a_dropped_postgresql_connection_fails_one_statement_and_the_next_reconnects(tmp_path, postgres_server,
                                                                                    postgres_url):
    store = JobStore(tmp_path, postgres_url)
    job = store.create({}, None)
    assert postgres_server.drop_connections(postgres_url) == 1
    with pytest.raises(StoreUnavailable, match="the job database at postgresql://renderloop@127.0.0.1"):
        store.get(job.id)
    assert store.claim(job.id) and store.get(job.id).state == RUNNING
    store.close()


def test_an_unsupported_database_url_is_refused(tmp_path):
    with pytest.raises(ValueError, match="unsupported job database 'mysql://db/jobs'"):
        JobStore(tmp_path, "mysql://db/jobs")


def test_an_unreachable_postgresql_server_is_named_without_its_password(tmp_path):
    url = f"postgresql://render:s3cret@127.0.0.1:{free_port()}/jobs"
    with pytest.raises(StoreUnavailable, match=r"cannot connect to PostgreSQL at postgresql://render:\*\*\*@") as caught:
        JobStore(tmp_path, url)
    assert "s3cret" not in str(caught.value)


def test_list_is_newest_first_and_filters_by_state(store):
    a, b = store.create({}, None), store.create({}, None)
    store.claim(b.id)
    assert [r.id for r in store.list()] == [b.id, a.id]
    assert [r.id for r in store.list(state=RUNNING)] == [b.id]


def test_artifacts_roundtrip(tmp_path):
    files = JobFiles(tmp_path / "job")
    lam = np.full((4, 6), 3.0, dtype=np.float32)
    files.save_lambda(lam)
    np.testing.assert_array_equal(files.load_lambda(), lam)
    assert files.load_preview(0) is None
    files.save_preview(0, Preview(version=7, layers={"denoised": np.ones((4, 6, 3), np.float32), "error": None}))
    preview = files.load_preview(0)
    assert preview.version == 7 and preview.layers["error"] is None
    assert preview.layers["denoised"].shape == (4, 6, 3)
    assert not files.checkpoint.exists()


# A thread's trivial work: seconds only on a loaded 2-core machine; the wait ends as soon as it is done.
WAIT_SECONDS = 60


def test_latest_wins_skips_superseded_requests():
    applied: list[int] = []
    gate = threading.Event()

    def apply(value: int) -> int:
        gate.wait(WAIT_SECONDS)
        applied.append(value)
        return value * 10

    box = LatestWins(apply)
    tickets = [box.submit(v) for v in range(5)]  # the first is in flight, the rest pile up
    gate.set()
    results = [box.wait(t, timeout=WAIT_SECONDS) for t in tickets]
    assert applied[-1] == 4 and len(applied) <= 2  # 1..3 were replaced before they ran
    assert results[-1] == 40 and all(r in (0, 40) for r in results)


def test_latest_wins_drops_a_request_ordered_before_one_already_seen():
    applied: list[str] = []
    box = LatestWins(lambda value: applied.append(value) or value)
    newer = box.submit("third", order=3)
    assert box.wait(newer, timeout=WAIT_SECONDS) == "third"
    late = box.submit("second", order=2)  # issued before "third", arrived after it
    assert box.wait(late, timeout=WAIT_SECONDS) == "third" and applied == ["third"]
    assert box.wait(box.submit("unordered"), timeout=WAIT_SECONDS) == "unordered"  # no order: arrival decides
    assert box.wait(box.submit("fourth", order=4), timeout=WAIT_SECONDS) == "fourth"


def test_latest_wins_reports_failures():
    def apply(value: int) -> int:
        raise ValueError(f"bad {value}")

    box = LatestWins(apply)
    with pytest.raises(ValueError, match="bad 1"):
        box.wait(box.submit(1), timeout=WAIT_SECONDS)


# -- quotas, idempotency, priority, leases ------------------------------------------------------

def test_a_database_made_before_leases_and_quotas_is_migrated(tmp_path, db_url):
    new = {"effects", "priority", "client", "idempotency_key", "lease_owner", "lease_expires_at"}
    first_release = replace(JOBS, columns=tuple(c for c in JOBS.columns if c.name not in new), added=(), unique=())
    old = open_database(tmp_path, db_url)
    old.ensure_schema(first_release)
    old.execute("INSERT INTO jobs (id, state, spec, created_at) VALUES (?, ?, ?, ?)", ("old", QUEUED, "{}", 1.0))
    old.close()
    store = JobStore(tmp_path, db_url)
    assert store.get("old").priority == 0 and store.get("old").lease_owner is None
    assert store.claim("old") and store.get("old").lease_owner == store.owner
    store.close()


def test_higher_priority_queued_jobs_are_claimed_first_then_the_oldest(store):
    low = store.create({"priority": -5}, None)
    first_default, second_default = store.create({}, None), store.create({"priority": 0}, None)
    urgent = store.create({"priority": 7}, None)
    order = []
    while (job_id := store.next_queued()) is not None:
        assert store.claim(job_id)
        order.append(job_id)
    assert order == [urgent.id, first_default.id, second_default.id, low.id]
    assert store.get(urgent.id).priority == 7


def test_a_repeated_idempotency_key_gives_back_the_first_job_and_creates_no_second(store):
    first = store.create({}, None, client="token:a", idempotency_key="k1")
    with pytest.raises(AlreadySubmitted) as repeat:
        store.create({}, None, client="token:a", idempotency_key="k1")
    assert repeat.value.record.id == first.id
    other_client = store.create({}, None, client="token:b", idempotency_key="k1")  # keys are per client
    assert other_client.id != first.id and len(store.list()) == 2
    assert store.find_submitted("token:a", "k1").id == first.id and store.find_submitted("token:a", "k2") is None


def test_the_unique_index_refuses_a_second_row_with_the_same_client_and_key(tmp_path, db_url):
    """The index, not only the look-up before the insert, holds when two servers race."""
    store = JobStore(tmp_path, db_url)
    store.create({}, None, client="c", idempotency_key="k")
    with pytest.raises(DuplicateKey):
        store._db.execute("INSERT INTO jobs (id, state, spec, created_at, client, idempotency_key) "
                          "VALUES (?, ?, ?, ?, ?, ?)", ("x", QUEUED, "{}", 1.0, "c", "k"))
    store.close()


def test_the_queue_caps_refuse_beyond_the_server_total_and_the_per_client_cap(store):
    quotas = Quotas(max_queued=3, max_queued_per_client=2, retry_after_seconds=7)
    store.create({}, None, client="a", quotas=quotas)
    store.create({}, None, client="a", quotas=quotas)
    with pytest.raises(QuotaExceeded, match="cap per client is 2") as caught:
        store.create({}, None, client="a", quotas=quotas)
    assert caught.value.retry_after == 7
    store.create({}, None, client="b", quotas=quotas)
    with pytest.raises(QuotaExceeded, match="queue is full"):
        store.create({}, None, client="c", quotas=quotas)
    assert store.claim(store.next_queued())  # a job that starts leaves the queue: room again
    store.create({}, None, client="c", quotas=quotas)


def test_a_claim_takes_a_lease_that_its_owner_renews(tmp_path, db_url):
    store = JobStore(tmp_path, db_url, leases=Leases(seconds=5))
    job = store.create({}, None)
    before = time.time()
    assert store.claim(job.id)
    claimed = store.get(job.id)
    assert claimed.lease_owner == store.owner and before + 5 <= claimed.lease_expires_at <= time.time() + 5
    time.sleep(0.05)
    assert store.renew_leases() == [job.id] and store.get(job.id).lease_expires_at > claimed.lease_expires_at
    store.close()


def test_only_a_lapsed_lease_is_requeued_and_not_a_live_servers(tmp_path, db_url):
    alive = JobStore(tmp_path, db_url, leases=Leases(seconds=60))
    # 2 s: opening the third store below took over 0.5 s on a loaded host, and the lease lapsed early.
    dying = JobStore(tmp_path, db_url, leases=Leases(seconds=2))
    theirs, lost = alive.create({}, None), alive.create({}, None)
    assert alive.claim(theirs.id) and dying.claim(lost.id)
    other = JobStore(tmp_path, db_url)  # a third server starting up
    assert other.requeue_abandoned() == []  # both leases hold (and both owners live in this process)
    while time.time() <= other.get(lost.id).lease_expires_at:  # the dying server stops renewing
        time.sleep(0.05)
    assert alive.renew_leases() == [theirs.id]
    assert other.requeue_lapsed() == [lost.id]
    assert other.get(lost.id).state == QUEUED and other.get(theirs.id).state == RUNNING
    assert dying.renew_leases() == []  # the job is no longer its to renew
    dying.requeue(theirs.id)  # nor to requeue
    assert other.get(theirs.id).state == RUNNING
    for s in (alive, dying, other):
        s.close()


def test_a_restart_requeues_at_once_the_jobs_of_a_dead_process_on_this_host(tmp_path, db_url):
    store = JobStore(tmp_path, db_url)
    job = store.create({}, None)
    store.claim(job.id)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    ghost = f"{socket.gethostname()}/{int(dead.stdout)}/feedbeef"  # a process that has exited
    store._db.execute("UPDATE jobs SET lease_owner = ? WHERE id = ?", (ghost, job.id))
    assert store.get(job.id).lease_expires_at > time.time() + 10  # its lease has not lapsed
    assert store.requeue_abandoned() == [job.id] and store.get(job.id).state == QUEUED
    store.close()
