"""Progress bars of the ``liecontrol`` commands (tqdm, on stderr).

* :func:`bar` — a tqdm bar, or a no-op one when ``quiet``;
* :func:`sb3_callback` — a stable-baselines3 callback that advances a bar by the environment steps done;
* :class:`TrainingProgress` — one bar per training run, advanced by the lines :func:`learning.baselines.train`
  logs at each learning-curve evaluation (``"... 4096 steps, eval return ..."``); the lines may come from
  worker processes through a queue (:meth:`TrainingProgress.drain`).
"""

from __future__ import annotations

import re
import sys
import threading

from tqdm.auto import tqdm

__all__ = ["bar", "sb3_callback", "TrainingProgress", "STEPS_IN_LOG", "write"]

#: the environment step count in a line of :func:`learning.baselines.train`'s log
STEPS_IN_LOG = re.compile(r": (\d+) steps, eval return ")


def bar(total: int | None, desc: str, quiet: bool = False, unit: str = "step", **kw) -> tqdm:
    """A tqdm progress bar on stderr (``disable=quiet``: then every call on it does nothing)."""
    return tqdm(total=total, desc=desc, unit=unit, disable=quiet, dynamic_ncols=True, **kw)


def sb3_callback(progress: tqdm):
    """An SB3 callback moving ``progress`` to the agent's environment step count after every step."""
    from stable_baselines3.common.callbacks import BaseCallback

    class _Progress(BaseCallback):
        def _on_step(self) -> bool:
            if progress.total is not None and self.num_timesteps > progress.total:
                progress.total = self.num_timesteps  # PPO collects whole rollouts, past a small budget
            progress.update(self.num_timesteps - progress.n)
            return True

    return _Progress()


class TrainingProgress:
    """One bar per training run (``key``: e.g. ``("ppo", 0)``), each over its step budget.

    :meth:`line` takes one line of a run's log: the bar moves to the step count it names, and the line goes
    to ``log`` (if given).  :meth:`drain` does that for ``(key, line)`` items of a
    queue, in a thread, until :meth:`close` (which puts the sentinel ``None``).
    """

    def __init__(self, budgets: dict, quiet: bool = False, label=str, log=None):
        self.log = log
        self.bars = {k: bar(b, label(k), quiet, leave=True, position=i)
                     for i, (k, b) in enumerate(budgets.items())}
        self._queue = None
        self._thread = None

    def line(self, key, text: str) -> None:
        m = STEPS_IN_LOG.search(text)
        b = self.bars.get(key)
        if m and b is not None:
            n = int(m.group(1))
            if b.total is not None:  # PPO ends at a whole rollout, past its budget
                b.total = max(b.total, n)
            b.update(n - b.n)
        if self.log is not None:
            self.log(text)

    def drain(self, queue) -> None:
        """Read ``(key, line)`` items from ``queue`` in a background thread until :meth:`close`."""
        self._queue = queue

        def loop():
            while (item := queue.get()) is not None:
                self.line(*item)

        self._thread = threading.Thread(target=loop, daemon=True)
        self._thread.start()

    def close(self, wait: bool = True) -> None:
        """Close the bars; with ``wait``, stop the drain thread through the queue first.  Without (the
        workers were killed: one may have died holding the queue's write lock, and a put would then block
        forever) the daemon thread is left to end with the process."""
        if self._thread is not None and wait:
            self._queue.put(None)
            self._thread.join(timeout=5)
        for b in self.bars.values():
            b.close()


def write(line: str) -> None:
    """Print ``line`` on stderr above the progress bars."""
    tqdm.write(line, file=sys.stderr)
