"""Launching a worker script under ``python -m torch.distributed.run`` for the distributed tests (no test
here)."""

import os
import signal
import subprocess
import sys
from pathlib import Path

__all__ = ["ROOT", "torchrun", "load_worker"]

ROOT = Path(__file__).resolve().parents[2]


def torchrun(worker: Path, args: list[str], *, timeout: float = 300, nproc: int = 2, meanwhile=None):
    """Run ``worker`` on ``nproc`` local processes (``--standalone``, one thread each, the repository on
    ``PYTHONPATH``); call ``meanwhile()`` (e.g. the single-process reference) while they run.

    Returns ``(returncode, log, meanwhile's result)``.  The launch gets a session of its own, so that on a
    timeout (a rank left waiting in a collective) the launcher *and* its workers are killed: killing the
    launcher alone leaves the workers holding the output pipe, and the wait for them never ends."""
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={nproc}",
           str(worker), *args]
    p = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         start_new_session=True)
    try:
        ref = meanwhile() if meanwhile is not None else None
        log, _ = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        log, _ = p.communicate()
        return None, log, None
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.communicate()
    return p.returncode, log, ref


def load_worker(worker: Path):
    """The worker script as a module (its ``run`` functions give the single-process reference)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(worker.stem, worker)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
