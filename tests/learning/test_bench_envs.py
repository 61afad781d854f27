import json

import pytest

from liecontrol import cli


def test_bench_envs_writes_records_with_ratios(tmp_path):
    path = tmp_path / "envs.json"
    assert cli.main(["bench", "envs", "--tasks", "pendulum", "--num-envs", "2", "64", "--seconds", "0.02",
                     "--repeats", "1", "--max-sync-envs", "2", "--no-compile", "--json", str(path)]) == 0
    recs = json.loads(path.read_text())
    keys = {"env", "impl", "mode", "device", "num_envs", "steps_per_s"}
    assert recs and all(keys <= set(r) for r in recs)
    ours = [r for r in recs if r["impl"] == "ours"]
    assert {(r["mode"], r["num_envs"]) for r in ours} >= {("torch", 2), ("torch", 64), ("numpy", 64)}
    assert all(r["steps_per_s"] > 0 for r in ours)
    sync = {r["num_envs"]: r for r in recs if r["impl"] == "gymnasium-sync"}
    assert sync[2]["steps_per_s"] > 0 and sync[64]["steps_per_s"] is None and "skipped" in sync[64]["status"]
    r2 = next(r for r in ours if r["num_envs"] == 2 and r["mode"] == "torch")
    assert r2["vs_gymnasium_sync"] == pytest.approx(r2["steps_per_s"] / sync[2]["steps_per_s"], rel=1e-9)
    pool = [r for r in recs if r["impl"] == "envpool"]
    assert all(r["status"] == "ok" or r["status"].startswith(("missing", "failed")) for r in pool)
