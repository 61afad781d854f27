"""Suite-wide settings: one intra-op thread per test worker (``make test`` runs two workers on two
cores; more threads than cores makes OpenMP spin and every op crawl), and a hypothesis profile
without deadlines (timings on a shared CI machine are noise)."""

import os

import torch
from hypothesis import settings

torch.set_num_threads(int(os.environ.get("LIECONTROL_TEST_THREADS", "1")))
settings.register_profile("liecontrol", deadline=None, max_examples=25)
settings.load_profile("liecontrol")
