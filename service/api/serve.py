"""`renderloop serve`: the API on uvicorn with the embedded SQLite store under a data dir.

Also runnable as `python -m service.api.serve [--host --port --data-dir --concurrency]`, and
`app_from_env` is a uvicorn factory (`uvicorn --factory service.api.serve:app_from_env`)
reading RENDERLOOP_DATA_DIR / RENDERLOOP_CONCURRENCY.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from fastapi import FastAPI

from models.pretrained import Networks

DATA_DIR_ENV = "RENDERLOOP_DATA_DIR"
CONCURRENCY_ENV = "RENDERLOOP_CONCURRENCY"
DEFAULT_HOST, DEFAULT_PORT = "127.0.0.1", 8000


def default_data_dir() -> Path:
    return Path(os.environ.get(DATA_DIR_ENV) or "./data")


def app_from_env() -> FastAPI:
    from models.pretrained import load_networks
    from service.api.app import create_app
    from service.loop.tensors import configure_torch_threads

    configure_torch_threads()
    return create_app(default_data_dir(), networks=load_networks(),
                      concurrency=int(os.environ.get(CONCURRENCY_ENV, "1")))


def serve(host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, data_dir: Path | None = None, concurrency: int = 1,
          *, networks: Networks) -> None:
    import uvicorn

    from service.api.app import create_app

    data_dir = Path(data_dir) if data_dir is not None else default_data_dir()
    data_dir.mkdir(parents=True, exist_ok=True)
    uvicorn.run(create_app(data_dir, networks=networks, concurrency=concurrency), host=host, port=port, log_level="info")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default=DEFAULT_HOST)
    parser.add_argument("--port", type=int, default=DEFAULT_PORT)
    parser.add_argument("--data-dir", type=Path, default=None, help=f"default: ${DATA_DIR_ENV} or ./data")
    parser.add_argument("--concurrency", type=int, default=int(os.environ.get(CONCURRENCY_ENV, "1")))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="renderloop serve", description=__doc__.splitlines()[0])
    add_arguments(parser)
    args = parser.parse_args(argv)
    from models.pretrained import load_networks

    serve(args.host, args.port, args.data_dir, args.concurrency, networks=load_networks())


if __name__ == "__main__":
    main()
