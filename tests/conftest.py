"""Suite-wide settings: one intra-op thread per test worker (``make test`` runs two workers on two
cores; more threads than cores makes OpenMP spin and every op crawl), a hypothesis profile without
deadlines (timings on a shared CI machine are noise), and one cache of compiled programs for the whole
suite under ``.pytest_cache/`` (kept between runs, never in the user's home; ``LIECONTROL_CACHE`` set
outside wins)."""

import os
from pathlib import Path

import torch
from hypothesis import settings

torch.set_num_threads(int(os.environ.get("LIECONTROL_TEST_THREADS", "1")))
settings.register_profile("liecontrol", deadline=None, max_examples=25)
settings.load_profile("liecontrol")
_ROOT = Path(__file__).resolve().parent.parent
os.environ.setdefault("LIECONTROL_CACHE", str(_ROOT / ".pytest_cache" / "aoti"))
