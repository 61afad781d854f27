import numpy as np
import pytest
import torch
from scipy import stats

from learning._counter_rng import keys_of_seeds, mix64, uniforms

M64 = np.uint64(0xFFFFFFFFFFFFFFFF)


def _mix64_numpy(z: np.ndarray) -> np.ndarray:
    """SplitMix64 in numpy uint64 arithmetic (defined wrap-around): the reference."""
    with np.errstate(over="ignore"):
        z = z + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return z ^ (z >> np.uint64(31))


def test_mix64_matches_uint64_reference_including_wraparound():
    rng = np.random.default_rng(0)
    z = rng.integers(0, 2**64, size=10000, dtype=np.uint64)
    z[:4] = [0, 1, 2**63, 2**64 - 1]
    ours = mix64(torch.from_numpy(z.view(np.int64))).numpy().view(np.uint64)
    np.testing.assert_array_equal(ours, _mix64_numpy(z))
    # the first SplitMix64 output from state 0 (published reference value)
    assert int(ours[0]) == 0xE220A8397B1DCDAF


def test_uniforms_are_uniform_and_independent():
    N = 20000
    key = keys_of_seeds(torch.arange(N))
    u = uniforms(key, torch.zeros(N, dtype=torch.int64), 3, torch.float64).numpy()
    assert u.min() >= 0.0 and u.max() < 1.0
    for j in range(3):
        assert stats.kstest(u[:, j], "uniform").pvalue > 1e-3
    assert abs(np.corrcoef(u[:, 0], u[:, 1])[0, 1]) < 0.03
    v = uniforms(key, torch.ones(N, dtype=torch.int64), 3, torch.float64).numpy()  # next episode
    assert abs(np.corrcoef(u[:, 0], v[:, 0])[0, 1]) < 0.03


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_uniforms_depend_only_on_key_and_episode(dtype):
    key = keys_of_seeds(torch.tensor([5, 7, 9]))
    ep = torch.tensor([0, 3, 1])
    full = uniforms(key, ep, 2, dtype)
    for i in range(3):  # batch composition does not matter
        assert torch.equal(uniforms(key[i:i + 1], ep[i:i + 1], 2, dtype), full[i:i + 1])
    assert full.dtype == dtype
