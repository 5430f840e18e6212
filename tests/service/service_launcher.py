"""Start the API server for the tests: `python service_launcher.py PORT`.

It runs exactly what `uvicorn --factory service.api.serve:app_from_env` runs (the shipped
weights, or $RENDERLOOP_WEIGHTS_DIR when a test sets it), on 127.0.0.1:PORT; with
RENDERLOOP_TEST_HOLD set, matching jobs hold inside a render until stopped (iteration_hold.py).
"""
from __future__ import annotations

import os
import sys

import uvicorn

import iteration_hold
from service.api.serve import SHUTDOWN_GRACE_SECONDS, app_from_env


def main(port: int) -> None:
    if os.environ.get(iteration_hold.ENV):
        iteration_hold.install(os.environ[iteration_hold.ENV])
    uvicorn.run(app_from_env(), host="127.0.0.1", port=port, log_level="warning",
                timeout_graceful_shutdown=SHUTDOWN_GRACE_SECONDS)


if __name__ == "__main__":
    main(int(sys.argv[1]))
