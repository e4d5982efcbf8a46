"""The approach network: labels from the full meshes, a network that learns them, and the
planner's use of its ranking."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("ompl")

from omnihang_jax import approach, planner, retreats  # noqa: E402


def test_a_ring_on_a_rod_comes_off_along_the_rod_not_straight_up():
    """The labels are the full meshes' word: a ring threaded on a rod cannot be lifted 4.5 cm
    straight up (the rod goes through it), but slides off along the rod towards its tip; the
    first free direction in the planner's order is the one find_retreat takes."""
    from tests.test_planner import ring_on_rod

    scene, goal, peg = ring_on_rod()
    labels = approach.approach_labels(scene, goal[None])[0]
    assert labels.shape == (26,)
    up = np.flatnonzero(np.all(np.isclose(approach.DIRECTIONS, [0, 0, 1]), axis=1))[0]
    assert not labels[up]
    along = np.asarray(peg.tip) - np.asarray(peg.base)
    along /= np.linalg.norm(along)
    outward = int(np.argmax(approach.DIRECTIONS @ along))
    assert labels[outward]
    assert labels.sum() < 13  # most directions run into the rod, the ring or the wall
    mesh = planner.MeshChecker(scene)
    found = retreats.find_retreat(mesh, goal, [0.045], 0.002, planner.default_bounds(scene))
    np.testing.assert_allclose(found.direction, approach.DIRECTIONS[np.argmax(labels)])


def test_free_retreats_respects_bounds_and_the_checker():
    """A floor at z < -1.5 cm for a 1-cm sphere: every direction with a downward part is
    blocked within 4.5 cm, the rest free, and bounds that end 1 cm above the goal block up."""
    floor = planner.AnalyticChecker([([-1, -1, -1], [1, 1, -0.015])], radius=0.01)
    goal = np.array([0.0, 0.0, 0.0, 1, 0, 0, 0])
    free = retreats.free_retreats(floor, goal, 0.045, 0.002)
    np.testing.assert_array_equal(free, approach.DIRECTIONS[:, 2] >= 0)
    low = (np.array([-1.0, -1, -1]), np.array([1.0, 1, 0.01]))
    capped = retreats.free_retreats(floor, goal, 0.045, 0.002, low)
    np.testing.assert_array_equal(capped, free & (approach.DIRECTIONS[:, 2] <= 0))


def _plate_data(n_pairs: int, rng):
    """Synthetic pairs: a small object cloud at the goal and a plate of support points 2 cm
    from it on one of six sides; an approach is free when it moves away from the plate."""
    sides = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0.0]])
    obj, sup, pair, goals, labels, names = [], [], [], [], [], []
    u = np.stack(np.meshgrid(np.linspace(-0.06, 0.06, 12), np.linspace(-0.06, 0.06, 12)), -1).reshape(-1, 2)  # fmt: skip
    for i in range(n_pairs):
        side = sides[i % 6]
        a = np.eye(3)[np.argmax(np.abs(side) < 0.5)]  # a vector across the plate
        b = np.cross(side, a)
        centre = rng.uniform(-0.1, 0.1, 3)
        plate = centre + 0.02 * side + u[:, :1] * a + u[:, 1:] * b
        obj.append(rng.normal(scale=0.008, size=(144, 3)))
        sup.append(plate + rng.normal(scale=5e-4, size=plate.shape))
        for _ in range(3):
            pair.append(i)
            goals.append([*centre, 1, 0, 0, 0])
            labels.append(approach.DIRECTIONS @ side < -0.6)
        names.append(f"plate_{i}")
    from experiments.train_approach import ApproachData

    return ApproachData(np.stack(obj).astype(np.float32), np.stack(sup).astype(np.float32),
                        np.array(pair, np.int32), np.array(goals, np.float32), np.array(labels),
                        names)  # fmt: skip


def test_the_approach_network_learns_which_side_is_blocked():
    """Prove learning by learning: on synthetic plates the tiny network's validation loss falls
    and its best direction is free far more often than the prior's single direction."""
    from experiments import train_approach

    rng = np.random.default_rng(0)
    data = _plate_data(48, rng)
    val = _plate_data(12, np.random.default_rng(1))
    cfg = approach.PRESETS["tiny"]
    params, log, prior = train_approach.train(
        data, val, cfg, steps=400, batch=16, learning_rate=3e-3, seed=0, time_budget=600,
        val_every=400, val_rows=36, progress=False,
    )  # fmt: skip
    first, last = log["val_history"][0], log["val_history"][-1]
    assert last["val_loss"] < 0.7 * first["val_loss"]
    assert last["top1_free"] >= 0.9 and last["prior_free"] < 0.4


def test_predictor_orders_directions_and_refuses_nan(tmp_path):
    import jax

    cfg = approach.PRESETS["tiny"]
    params = approach.make_approach_net(cfg).init(jax.random.key(0))
    approach.save(tmp_path, cfg, params, steps=0)
    cfg2, params2, meta = approach.load(tmp_path)
    assert cfg2 == cfg and meta["steps"] == 0
    pred = approach.ApproachPredictor(cfg2, params2)
    rng = np.random.default_rng(0)
    obj, sup = rng.normal(scale=0.02, size=(300, 3)), rng.normal(scale=0.05, size=(500, 3))
    goal = np.array([0.0, 0.0, 0.05, 1, 0, 0, 0])
    directions, probs = pred.order(obj, sup, goal)
    assert directions.shape == (26, 3) and np.all(np.diff(probs) <= 0)
    raw = approach.ApproachPredictor(cfg, params).probabilities(obj, sup, goal)
    np.testing.assert_allclose(np.sort(raw)[::-1], probs, rtol=1e-6)
    bad = obj.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="object cloud"):
        pred.order(bad, sup, goal)
    with pytest.raises(FileNotFoundError, match="train_approach"):
        approach.load(tmp_path / "missing")


@pytest.mark.slow  # several networks and cloud subsets: a handful of compilations
def test_predictor_averages_networks_and_cloud_subsets(tmp_path):
    """A list of networks and ``views`` > 1 average the probabilities of each network on each
    cloud subset (seeds 0..views-1), computed here one by one."""
    import jax

    from omnihang_jax import collision

    cfg = approach.PRESETS["tiny"]
    nets = [approach.make_approach_net(cfg).init(jax.random.key(k)) for k in (0, 1)]
    rng = np.random.default_rng(0)
    obj, sup = rng.normal(scale=0.02, size=(300, 3)), rng.normal(scale=0.05, size=(500, 3))
    goal = np.array([0.0, 0.0, 0.05, 1, 0, 0, 0])
    f = approach.jitted_probabilities(cfg)
    by_hand = np.mean([
        np.asarray(f(p, collision.subsample_cloud(obj, cfg.local_from, s),
                     collision.subsample_cloud(sup, cfg.local_from, s), goal[None]))[0]
        for p in nets for s in range(3)
    ], axis=0)  # fmt: skip
    both = approach.ApproachPredictor(cfg, nets, views=3).probabilities(obj, sup, goal)
    np.testing.assert_allclose(both, by_hand, rtol=1e-5)
    one = approach.ApproachPredictor(cfg, nets[0]).probabilities(obj, sup, goal)
    seed0 = f(nets[0], collision.subsample_cloud(obj, cfg.local_from),
              collision.subsample_cloud(sup, cfg.local_from), goal[None])  # fmt: skip
    np.testing.assert_array_equal(one, np.asarray(seed0)[0])  # one network, one view: as before
    assert not np.allclose(one, both)  # another network and other subsets: other numbers
    # load_predictor: several folders, the threshold given overrides the first config's
    for k, p in enumerate(nets):
        approach.save(tmp_path / f"n{k}", cfg, p, steps=0)
    loaded = approach.load_predictor([str(tmp_path / "n0"), str(tmp_path / "n1")], 0.77, views=3)
    assert loaded.config.threshold == 0.77 and loaded.views == 3
    np.testing.assert_allclose(loaded.probabilities(obj, sup, goal), by_hand, rtol=1e-5)
    single = approach.load_predictor(str(tmp_path / "n0"))
    assert single.config.threshold == cfg.threshold
    np.testing.assert_array_equal(single.probabilities(obj, sup, goal), one)
    with pytest.raises(ValueError, match="views"):
        approach.ApproachPredictor(cfg, nets, views=0)
    with pytest.raises(ValueError, match="configs"):
        approach.ApproachPredictor(cfg, nets, configs=[cfg])


def test_ranking_figures_and_the_whole_object_split():
    from experiments.train_approach import object_split, ranking_figures

    labels = np.zeros((4, 26), bool)
    labels[0, 1] = labels[1, 0] = labels[2, [0, 1]] = True  # goal 3: no free approach
    prob = np.full((4, 26), 0.1)
    prob[0, 1], prob[1, 5], prob[2, 0], prob[3, 2] = 0.9, 0.6, 0.3, 0.8
    prior = np.eye(26)[0]  # the prior always says direction 0
    out = ranking_figures(prob, labels, prior, threshold=0.5)
    assert out["any_free"] == 0.75 and out["top1_free"] == 0.5  # goals 0 and 2
    assert out["top1_free_when_any"] == round(2 / 3, 4) and out["prior_free"] == 0.5
    assert out["used"] == 0.75 and out["used_free"] == round(1 / 3, 4)  # goals 0, 1, 3 used
    names = [f"mug_{i:04d}" for i in range(200)]
    split = object_split(names, 7)
    assert 10 < split.sum() < 50 and np.array_equal(split, object_split(names, 7))
    assert np.array_equal(object_split(names[::-1], 7), split[::-1])  # by name, not position


def test_threshold_sweep_and_the_rule_threshold():
    from experiments import train_approach

    sweep = train_approach.threshold_sweep(np.array([[0.9, 0.1], [0.6, 0.2]]),
                                           np.array([[True, False], [False, True]]))  # fmt: skip
    assert train_approach.rule_threshold(sweep) == 0.65


def _route_data(n, rng, config):
    """The plates above with route labels: a route is free and off when each of its moves
    leaves the plate's open side (cosine with the blocked side < -0.6)."""
    data = _plate_data(n, rng)
    routes = config.routes
    dirs = approach.DIRECTIONS
    side = np.stack([-(dirs[lab].mean(0)) for lab in data.labels])  # the blocked side
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    last_ok = dirs[routes[:, 2].astype(int)] @ side.T < -0.6  # [R, rows]
    first = np.where(routes[:, :1] < 0, 0, routes[:, :1]).astype(int)[:, 0]
    first_ok = (dirs[first] @ side.T < -0.6) | (routes[:, :1] < 0)
    data.labels = (last_ok & first_ok).T
    return data


@pytest.mark.slow  # trains a 532-output network (~70 s on 2 cores)
def test_a_route_network_learns_routes_and_warm_starts_from_a_straight_one(tmp_path):
    """The route network (``first_lengths``) has one output per route of
    ``retreats.move_routes``; on synthetic plates it learns which routes leave the open side;
    ``warm_start`` copies every layer of a straight network and its one-move columns."""
    import dataclasses

    import jax

    from experiments import train_approach

    cfg = dataclasses.replace(approach.PRESETS["tiny"], first_lengths=(0.015,))
    assert cfg.outputs == 532 and len(cfg.routes) == 532
    data = _route_data(48, np.random.default_rng(0), cfg)
    val = _route_data(12, np.random.default_rng(1), cfg)
    straight = approach.PRESETS["tiny"]
    old = approach.make_approach_net(straight).init(jax.random.key(3))
    approach.save(tmp_path / "straight", straight, old, steps=0)
    fresh = approach.make_approach_net(cfg).init(jax.random.key(0))
    warm = train_approach.warm_start(fresh, tmp_path / "straight", cfg, data.labels.mean(0))
    np.testing.assert_allclose(warm["Dense_1"]["kernel"][:, :26], old["Dense_1"]["kernel"])
    for key in set(old) - {"Dense_1"}:  # every other layer is the straight network's
        jax.tree_util.tree_map(np.testing.assert_array_equal, warm[key], old[key])
    params, log, _ = train_approach.train(
        data, val, cfg, steps=300, batch=16, learning_rate=3e-3, seed=0, time_budget=600,
        val_every=300, val_rows=36, progress=False, init=str(tmp_path / "straight"),
    )  # fmt: skip
    first, last = log["val_history"][0], log["val_history"][-1]
    assert last["val_loss"] < 0.7 * first["val_loss"]
    assert last["top1_free"] >= 0.9
    approach.save(tmp_path / "routes", cfg, params, steps=300)
    pred = approach.load_predictor(tmp_path / "routes")
    assert pred.config.first_lengths == (0.015,)
    routes, probs = pred.best_routes(val.object_points[0], val.support_points[0], val.goals[0])
    assert routes.shape == (532, 3) and np.all(np.diff(probs) <= 0)
    with pytest.raises(ValueError, match="best_routes"):
        pred.order(val.object_points[0], val.support_points[0], val.goals[0])


def test_warm_start_from_a_route_network_keeps_its_last_layer(tmp_path):
    """A route network warm-started from one of the same routes takes every layer, the last
    included (more data, same outputs)."""
    import dataclasses

    import jax

    from experiments import train_approach

    cfg = dataclasses.replace(approach.PRESETS["tiny"], first_lengths=(0.015,))
    old = approach.make_approach_net(cfg).init(jax.random.key(5))
    approach.save(tmp_path / "routes", cfg, old, steps=0)
    fresh = approach.make_approach_net(cfg).init(jax.random.key(0))
    warm = train_approach.warm_start(fresh, tmp_path / "routes", cfg, np.full(cfg.outputs, 0.1))
    for key in old:
        jax.tree_util.tree_map(np.testing.assert_array_equal, warm[key], old[key])
