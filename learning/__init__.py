"""learning: gymnasium environments, batched rollouts, demonstrations and RL baselines built on
:mod:`controllers` (see ARCHITECTURE.md).  The package is reserved in this release; its modules
arrive with the learning issues."""

__all__: list[str] = []
