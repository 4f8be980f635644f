"""The embedded worker of `neudf serve`: `neudf worker` as a child process, restarted if it dies.

A separate process keeps training off the API's event loop and lets the worker use Celery's prefork
pool (time limits, a fresh process per job). It gets the app's settings through ``NEUDF_*`` variables,
so both sides agree on the data folder, database and broker, and this process's id as ``parent_pid``: a
worker whose `neudf serve` was killed outright (SIGKILL, the OOM killer) ends by itself and hands back its
job, instead of living on beside the next `neudf serve`'s worker (``worker.tasks.WorkerMonitor``).
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

from pydantic import SecretStr

from service.settings import Settings

log = logging.getLogger("neudf.service")


def settings_env(settings: Settings) -> dict[str, str]:
    """The environment that makes another process read the same settings."""
    env = dict(os.environ)
    for name, value in settings.model_dump().items():
        key = f"NEUDF_{name.upper()}"
        if value is None:
            env.pop(key, None)
        elif isinstance(value, SecretStr):
            env[key] = value.get_secret_value()
        elif isinstance(value, list):
            env[key] = ",".join(map(str, value))
        else:
            env[key] = str(value)
    env["NEUDF_DATA_DIR"] = str(settings.root)
    env["NEUDF_EMBEDDED_WORKER"] = "false"
    env["NEUDF_PARENT_PID"] = str(os.getpid())
    # The child must import this very code base, whichever way it was installed (or not).
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join([root, *filter(None, [env.get("PYTHONPATH")])])
    return env


def worker_command() -> list[str]:
    return [sys.executable, "-m", "worker.cli", "worker"]


class EmbeddedWorker:
    """Start, watch and stop one local worker process (and its pool children, as one process group)."""

    def __init__(self, settings: Settings, *, restart_delay_s: float = 2.0, stop_grace_s: float = 10.0) -> None:
        self.settings = settings
        self.restart_delay_s, self.stop_grace_s = restart_delay_s, stop_grace_s
        self.process: subprocess.Popen | None = None
        self._stopping = threading.Event()
        self._watcher = threading.Thread(target=self._watch, name="neudf-embedded-worker", daemon=True)
        self.restarts = 0

    def _spawn(self) -> None:
        log_file = open(self.settings.root / "worker.log", "ab")  # noqa: SIM115 - owned by the child
        self.process = subprocess.Popen(worker_command(), env=settings_env(self.settings), stdout=log_file,
                                        stderr=subprocess.STDOUT, start_new_session=True)
        log_file.close()
        log.info("embedded worker started (pid %d, log %s)", self.process.pid, self.settings.root / "worker.log")

    def start(self) -> None:
        self._spawn()
        self._watcher.start()

    def _watch(self) -> None:
        while not self._stopping.is_set():
            process = self.process
            if process is not None and process.poll() is not None and not self._stopping.is_set():
                log.warning("embedded worker exited with %s; starting a new one", process.returncode)
                self.restarts += 1
                if self._stopping.wait(self.restart_delay_s):
                    return
                self._spawn()
            self._stopping.wait(0.5)

    def stop(self) -> None:
        """Warm shutdown first; a job still running after the grace time is killed and resumes next start."""
        self._stopping.set()
        process = self.process
        if process is None or process.poll() is not None:
            return
        # SIGTERM to the worker itself (a warm shutdown: it stops its pool), SIGKILL to the group if it hangs.
        try:
            os.kill(process.pid, signal.SIGTERM)
            process.wait(self.stop_grace_s)
        except ProcessLookupError:
            pass
        except subprocess.TimeoutExpired:
            log.warning("embedded worker still busy after %.0f s; killing it (its job resumes next start)",
                        self.stop_grace_s)
        # The pool children share the group; make sure none outlives the worker.
        try:
            os.killpg(process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
