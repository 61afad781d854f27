"""learning.zoo: the published rl-baselines3-zoo rows, the best-agent lookup and the version aliases."""

from learning.zoo import ZOO_SCORES, zoo_best, zoo_scores


def test_best_is_the_highest_mean_and_aliases_read_the_published_version():
    for env, rows in ZOO_SCORES.items():
        algo, best = zoo_best(env)
        assert best == max(r[0] for r in rows.values()) and rows[algo][0] == best
        assert all(std >= 0 and steps[-1] in "kM" for _, std, steps in rows.values())
    assert zoo_best("Pendulum-v1") == ("td3", -151.855)
    assert zoo_best("MountainCarContinuous-v0") == ("ars", 96.672)
    assert zoo_scores("Hopper-v5") == zoo_scores("Hopper-v3") != {}
    assert zoo_best("InvertedPendulum-v5") is None and zoo_scores("Reacher-v5") == {}
