"""Uploaded files kept once (service/jobs/blobs.py) in a real job store's data dir: bundles made
of hard links to content-addressed blobs, counted once in the disk limits, released with the
last job that links to them."""
from __future__ import annotations

import os
import shutil

import pytest

from service.jobs.blobs import MIN_SHARED_BYTES, BlobStore, file_digest, freed_bytes, unique_bytes
from service.jobs.retention import Retention, folder_bytes, sweep
from service.jobs.store import JobStore
from service.render.sandbox import run_walled
from required_components import require_component

MIB = 2**20


def bundle_job(store: JobStore, source) -> str:
    """A job whose bundle is a copy of `source`, adopted as an upload is."""
    record = store.create({"scene": "scene.xml", "bundle_scene": "scene.xml"}, 1.0)
    bundle = store.job_dir(record.id) / "bundle"
    shutil.copytree(source, bundle)
    BlobStore(store.data_dir).adopt(bundle)
    return record.id


def make_bundle(folder, texture_bytes: int = 2 * MIB):
    folder.mkdir()
    (folder / "scene.xml").write_text("<scene version='3.0.0'/>")
    (folder / "textures").mkdir()
    (folder / "textures" / "wall.bin").write_bytes(os.urandom(texture_bytes))
    return folder


def test_twelve_jobs_of_one_bundle_keep_one_copy_and_the_last_delete_frees_it(tmp_path):
    store = JobStore(tmp_path / "data")
    source = make_bundle(tmp_path / "upload", texture_bytes=4 * MIB)
    bundle_size = folder_bytes(source)
    before = folder_bytes(store.data_dir)
    jobs = [bundle_job(store, source) for _ in range(12)]
    blobs = BlobStore(store.data_dir)
    assert len(blobs.blobs()) == 1  # the texture, once (scene.xml is under MIN_SHARED_BYTES: each job's own)
    texture = blobs.path_of(file_digest(source / "textures" / "wall.bin"))
    assert texture.stat().st_nlink == 13  # its own name and one link per job
    grown = folder_bytes(store.data_dir) - before
    assert bundle_size <= grown < bundle_size + MIB  # one bundle, not twelve (the rest: SQLite's journal)
    assert os.stat(store.job_dir(jobs[0]) / "bundle" / "textures" / "wall.bin").st_mode & 0o222 == 0  # read-only

    for job_id in jobs[:-1]:
        store.delete(job_id)
        blobs.release_unused()
    assert len(blobs.blobs()) == 1 and texture.stat().st_nlink == 2  # the last job still uses it
    assert freed_bytes(store.job_dir(jobs[-1])) == bundle_size  # what deleting it would free
    store.delete(jobs[-1])
    assert [p.name for p in blobs.release_unused()] and blobs.blobs() == []
    assert folder_bytes(store.data_dir) < before + MIB and unique_bytes(store.jobs_dir) == 0


def test_a_different_file_gets_its_own_blob_and_the_same_content_under_another_name_shares(tmp_path):
    store = JobStore(tmp_path / "data")
    first = make_bundle(tmp_path / "a", texture_bytes=MIN_SHARED_BYTES)
    second = tmp_path / "b"
    shutil.copytree(first, second)
    (second / "textures" / "copy.bin").write_bytes((first / "textures" / "wall.bin").read_bytes())
    (second / "textures" / "other.bin").write_bytes(os.urandom(MIN_SHARED_BYTES))
    (second / "textures" / "small.bin").write_bytes(os.urandom(MIN_SHARED_BYTES - 1))
    jobs = [bundle_job(store, first), bundle_job(store, second)]
    assert len(BlobStore(store.data_dir).blobs()) == 2  # wall.bin (= copy.bin) and other.bin
    small = store.job_dir(jobs[1]) / "bundle" / "textures" / "small.bin"
    assert small.stat().st_nlink == 1  # under MIN_SHARED_BYTES: the job's own copy


def test_the_disk_cap_counts_shared_files_once_and_the_sweep_releases_their_blobs(tmp_path):
    store = JobStore(tmp_path / "data")
    source = make_bundle(tmp_path / "upload")
    jobs = [bundle_job(store, source) for _ in range(4)]
    for job_id in jobs:
        assert store.claim(job_id)
        store.finish(job_id, "completed")
    used = folder_bytes(store.data_dir)
    assert used < 2 * folder_bytes(source)  # four jobs, one copy: under a cap of two bundles
    assert sweep(store, Retention(max_disk_bytes=used)) == []
    removed = sweep(store, Retention(max_disk_bytes=folder_bytes(source) // 2))
    assert len(removed) == 4 and BlobStore(store.data_dir).blobs() == []
    assert unique_bytes(store.jobs_dir) == 0


def test_the_scene_sandbox_reads_a_job_s_links_but_not_the_blobs_they_share(tmp_path):
    require_component("landlock")
    store = JobStore(tmp_path / "data")
    job_id = bundle_job(store, make_bundle(tmp_path / "upload"))
    bundle = store.job_dir(job_id) / "bundle"
    blob = BlobStore(store.data_dir).blobs()[0]

    def read_both() -> tuple[int, str]:
        size = len((bundle / "textures" / "wall.bin").read_bytes())  # the job's own name: inside its wall
        try:
            blob.read_bytes()
            return size, "blob read"
        except PermissionError:
            return size, "blob refused"

    assert run_walled(read_both, [bundle]) == (2 * MIB, "blob refused")
