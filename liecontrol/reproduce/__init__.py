"""Reproductions of the experiments of the seed papers."""
