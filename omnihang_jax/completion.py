"""Shape completion of a partial cloud (issue 13: the hidden backs the planner's checkers miss).

Why: the hybrid planner's colliding paths meet the support where neither camera looked. In the
twenty-fourth session's probes (docs/paths.md) all 13 support contacts of its colliding paths
lay 2-41 mm behind an observed support surface and 12 of 13 had no observed object point
within 3 mm: the object's hidden back met the support's hidden back. No test on the observed
clouds can see that; a completed shape can.

The network is PCN's encoder-decoder (Yuan et al., "PCN: Point Completion Network", 3DV 2018)
in its coarse form: a two-stage PointNet encoder (shared MLP, max pool, the pooled feature
concatenated back onto every point, shared MLP, max pool), an MLP decoder to ``n_coarse``
points and its folding stage (a small 2-D grid around each coarse point, moved by a shared MLP)
to ``n_output`` points. One network per body kind (object: its own frame, any view; support: the world
frame, views from the front), trained with the symmetric Chamfer distance against the body's
whole surface (``sim.camera.surface_cloud``: the union of 42 views). Inputs are centred on
their mean and divided by ``scale`` inside the network; the output is moved back, so the
completed points are in the input cloud's frame. The planner uses ``observed + predicted``.

Pure functions: ``make_completion(config) -> (init, apply)``; ``complete_fn(config)(params,
clouds [B, N, 3]) -> [B, M, 3]``; ``chamfer`` / ``coverage`` are the loss and the metrics.
``train_completion`` is the host loop (validation curve, cosine schedule, resumable).
For the planner: ``predict_points`` (optionally carved with the cameras, ``carve``;
``predict_points_many`` for a dataset's pairs), ``clearance_clouds`` (the clouds a clearance
test on completed shapes uses) and ``completed_cloud`` (the input of a completion-aware NCE).
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import flax.linen as nn
import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np
import optax

from omnihang_jax import checkpoints

KINDS = ("object", "support")
WEIGHTS_FILE = "params.msgpack"


@dataclasses.dataclass(frozen=True)
class CompletionConfig:
    kind: str = "object"  # "object" (object frame) or "support" (world frame)
    n_input: int = 1024  # observed points fed to the network (a random subset)
    scale: float = 0.1  # m: centred coordinates are divided by this inside the network
    encoder: tuple[int, ...] = (64, 128)  # first shared MLP (then max pool)
    encoder2: tuple[int, ...] = (256, 512)  # second shared MLP on [point, pooled] (max pool)
    decoder: tuple[int, ...] = (512, 512)  # MLP from the global feature to the coarse points
    n_coarse: int = 256  # coarse points (PCN's first output)
    fold: tuple[int, int] = (2, 4)  # a grid of offsets folded around each coarse point
    fold_size: float = 0.05  # the grid's half-width in network units (x scale: 5 mm)
    fine: tuple[int, ...] = (256, 256)  # shared MLP of the folding stage

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {self.kind!r}")
        if min(self.n_input, self.n_coarse, *self.fold) < 1 or self.scale <= 0:
            raise ValueError(f"bad sizes in {self}")

    @property
    def n_output(self) -> int:
        return self.n_coarse * self.fold[0] * self.fold[1]


class _PCN(nn.Module):
    config: CompletionConfig

    @nn.compact
    def __call__(self, x: jax.Array):  # [B, N, 3] normalised -> coarse [B, C, 3], fine [B, M, 3]
        cfg = self.config
        f = x
        for i, w in enumerate(cfg.encoder):
            f = nn.Dense(w, name=f"enc1_{i}")(f)
            if i < len(cfg.encoder) - 1:
                f = nn.relu(f)
        g = jnp.max(f, axis=1, keepdims=True)
        f = jnp.concatenate([f, jnp.broadcast_to(g, f.shape)], axis=-1)
        for i, w in enumerate(cfg.encoder2):
            f = nn.Dense(w, name=f"enc2_{i}")(f)
            if i < len(cfg.encoder2) - 1:
                f = nn.relu(f)
        glob = jnp.max(f, axis=1)  # [B, G]
        h = glob
        for i, w in enumerate(cfg.decoder):
            h = nn.relu(nn.Dense(w, name=f"dec_{i}")(h))
        b = x.shape[0]
        coarse = nn.Dense(cfg.n_coarse * 3, name="coarse")(h).reshape(b, cfg.n_coarse, 3)
        # folding: each coarse point carries a small 2-D grid; a shared MLP on [global feature,
        # grid offset, coarse point] moves every grid point (PCN's fine stage)
        u = jnp.linspace(-cfg.fold_size, cfg.fold_size, cfg.fold[0])
        v = jnp.linspace(-cfg.fold_size, cfg.fold_size, cfg.fold[1])
        grid = jnp.stack(jnp.meshgrid(u, v, indexing="ij"), -1).reshape(-1, 2)  # [F, 2]
        k = grid.shape[0]
        centres = jnp.repeat(coarse, k, axis=1)  # [B, C*F, 3]
        feats = jnp.concatenate([
            jnp.broadcast_to(glob[:, None, :], (b, cfg.n_coarse * k, glob.shape[-1])),
            jnp.broadcast_to(jnp.tile(grid, (cfg.n_coarse, 1))[None], (b, cfg.n_coarse * k, 2)),
            centres,
        ], axis=-1)  # fmt: skip
        for i, w in enumerate(cfg.fine):
            feats = nn.relu(nn.Dense(w, name=f"fine_{i}")(feats))
        fine = centres + nn.Dense(3, name="fine_out")(feats)
        return coarse, fine


def make_completion(config: CompletionConfig) -> tuple[Callable, Callable]:
    """(init(key) -> params, apply(params, clouds [B, N, 3]) -> (coarse [B, C, 3], fine
    [B, M, 3])), both in the clouds' frame."""
    net = _PCN(config)

    def init(key):
        return net.init(key, jnp.zeros((1, config.n_input, 3), jnp.float32))

    def apply(params, clouds):
        clouds = jnp.asarray(clouds, jnp.float32)
        centre = jnp.mean(clouds, axis=1, keepdims=True)
        coarse, fine = net.apply(params, (clouds - centre) / config.scale)
        return centre + config.scale * coarse, centre + config.scale * fine

    return init, apply


def complete_fn(config: CompletionConfig) -> Callable:
    """Jitted ``(params, clouds [B, N, 3]) -> predicted [B, M, 3]`` (the fine points)."""
    apply = make_completion(config)[1]
    return jax.jit(lambda params, clouds: apply(params, clouds)[1])


def _nearest(a: jax.Array, b: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Distances from each point of a [.., N, 3] to b [.., M, 3] and back: ([.., N], [.., M])."""
    sq = (
        jnp.sum(a * a, -1)[..., :, None]
        + jnp.sum(b * b, -1)[..., None, :]
        - 2.0 * jnp.einsum("...nc,...mc->...nm", a, b)
    )
    sq = jnp.maximum(sq, 0.0)
    return jnp.sqrt(jnp.min(sq, -1) + 1e-12), jnp.sqrt(jnp.min(sq, -2) + 1e-12)


def chamfer(pred: jax.Array, target: jax.Array) -> jax.Array:
    """Symmetric Chamfer distance (unsquared, metres): mean nearest distance pred -> target
    plus target -> pred, per cloud ([B, M, 3], [B, T, 3] -> [B])."""
    d_pt, d_tp = _nearest(pred, target)
    return jnp.mean(d_pt, -1) + jnp.mean(d_tp, -1)


def coverage(pred: jax.Array, target: jax.Array, observed: jax.Array, tol: float) -> dict:
    """Per cloud [B]: ``coverage`` = share of the target's surface within ``tol`` of observed +
    predicted points (what a checker can see), ``observed_coverage`` = the same with the
    observed points alone, ``accuracy`` = share of predicted points within ``tol`` of the
    target (the rest would be false surfaces), ``chamfer`` in metres."""
    both = jnp.concatenate([observed, pred], axis=1)
    _, d_both = _nearest(both, target)
    _, d_obs = _nearest(observed, target)
    d_pt, d_tp = _nearest(pred, target)
    return dict(
        coverage=jnp.mean(d_both < tol, -1),
        observed_coverage=jnp.mean(d_obs < tol, -1),
        accuracy=jnp.mean(d_pt < tol, -1),
        chamfer=jnp.mean(d_pt, -1) + jnp.mean(d_tp, -1),
    )


class CompletionData(NamedTuple):
    """Views of whole bodies: ``inputs`` [A, V, P, 3] partial clouds (P >= n_input),
    ``targets`` [A, T, 3] whole surfaces, ``names`` [A]."""

    inputs: np.ndarray
    targets: np.ndarray
    names: np.ndarray

    def take(self, idx) -> CompletionData:
        idx = np.asarray(idx, int)
        return CompletionData(self.inputs[idx], self.targets[idx], self.names[idx])

    def check(self, what: str) -> None:
        if self.inputs.ndim != 4 or self.inputs.shape[-1] != 3 or self.targets.ndim != 3:
            raise ValueError(f"{what}: inputs [A, V, P, 3] and targets [A, T, 3] expected, got "
                             f"{self.inputs.shape} and {self.targets.shape}")  # fmt: skip
        if len(self.inputs) != len(self.targets) or len(self.inputs) == 0:
            raise ValueError(f"{what}: {len(self.inputs)} inputs, {len(self.targets)} targets")
        for name, arr in (("inputs", self.inputs), ("targets", self.targets)):
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{what}: {name} hold NaN or inf")


def sample_batch(data: CompletionData, rng: np.random.Generator, batch: int, n_input: int):
    """(inputs [B, n_input, 3], targets [B, T, 3]): random bodies, views and point subsets."""
    a = rng.integers(0, len(data.inputs), batch)
    v = rng.integers(0, data.inputs.shape[1], batch)
    p = data.inputs.shape[2]
    pts = np.stack([rng.choice(p, n_input, replace=p < n_input) for _ in range(batch)])
    x = data.inputs[a[:, None], v[:, None], pts]
    return x.astype(np.float32), data.targets[a].astype(np.float32)


def fixed_views(data: CompletionData, n_input: int, views: int = 4, seed: int = 0):
    """The evaluation set: the first ``views`` views of every body, fixed point subsets."""
    rng = np.random.default_rng(seed)
    a, v = np.meshgrid(np.arange(len(data.inputs)), np.arange(min(views, data.inputs.shape[1])),
                       indexing="ij")  # fmt: skip
    a, v = a.ravel(), v.ravel()
    p = data.inputs.shape[2]
    pts = np.stack([rng.choice(p, n_input, replace=p < n_input) for _ in range(len(a))])
    return (
        data.inputs[a[:, None], v[:, None], pts].astype(np.float32),
        data.targets[a].astype(np.float32),
        a,
    )


@dataclasses.dataclass(frozen=True)
class CompletionTrainConfig:
    steps: int = 20000
    batch: int = 32
    lr: float = 1e-3
    warmup: int = 500
    weight_decay: float = 1e-5
    eval_every: int = 1000
    tol: float = 0.005  # m: coverage / accuracy tolerance (and twice it)
    seed: int = 0


def evaluate(apply, params, data: CompletionData, config: CompletionConfig, tol: float,
             views: int = 4, chunk: int = 64) -> dict:  # fmt: skip
    """Over ``fixed_views``: mean Chamfer (mm), and coverage, observed coverage and accuracy
    (:func:`coverage`) within ``tol`` and within twice ``tol`` (keys ``..._<mm>mm``)."""
    x, t, _ = fixed_views(data, config.n_input, views)
    out = {}
    for k, tl in enumerate((tol, 2 * tol)):
        fn = _eval_jit(apply, tl)
        rows = [jax.device_get(fn(params, x[i : i + chunk], t[i : i + chunk]))
                for i in range(0, len(x), chunk)]  # fmt: skip
        mean = {key: float(np.mean(np.concatenate([r[key] for r in rows]))) for key in rows[0]}
        if k == 0:
            out["chamfer_mm"] = 1e3 * mean["chamfer"]
        mm = f"{1e3 * tl:g}mm"
        out |= {f"{key}_{mm}": v for key, v in mean.items() if key != "chamfer"}
    return out


_EVAL_CACHE: dict = {}


def _eval_jit(apply, tol):
    key = (apply, tol)
    if key not in _EVAL_CACHE:
        _EVAL_CACHE[key] = jax.jit(lambda p, x, t: coverage(apply(p, x)[1], t, x, tol))
    return _EVAL_CACHE[key]


def save_completion(folder, config: CompletionConfig, params, **extra) -> None:
    from sim import atomic

    folder = Path(folder)
    atomic.write_atomic(folder / WEIGHTS_FILE,
                        lambda f: f.write(flax.serialization.to_bytes(jax.device_get(params))))  # fmt: skip
    meta = {"kind": "CompletionConfig", "config": dataclasses.asdict(config), **extra}
    atomic.write_text(folder / "config.json", json.dumps(meta, indent=2))


def load_completion(folder) -> tuple[CompletionConfig, dict, dict]:
    """(config, params, meta) of a folder written by :func:`save_completion`."""
    path = Path(folder) / "config.json"
    if not path.exists():
        raise FileNotFoundError(
            f"{path} not found: train it first (`python -m experiments.train_completion`)"
        )
    meta = json.loads(path.read_text())
    if meta.get("kind") != "CompletionConfig":
        raise ValueError(f"{path}: not a completion network ({meta.get('kind')!r})")
    raw = {k: tuple(v) if isinstance(v, list) else v for k, v in meta["config"].items()}
    config = CompletionConfig(**raw)
    init, _ = make_completion(config)
    params = flax.serialization.from_bytes(
        init(jax.random.key(0)), (Path(folder) / WEIGHTS_FILE).read_bytes()
    )
    # (a copy stored in float16 to travel light loads as float32)
    params = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float32), params)
    return config, params, meta


def train_completion(
    config: CompletionConfig,
    train: CompletionData,
    val: CompletionData,
    folder,
    tc: CompletionTrainConfig = CompletionTrainConfig(),
    progress: bool = True,
) -> dict:
    """Train one completion network; ``folder`` gets ``history.jsonl`` (train loss and the
    validation metrics every ``eval_every`` steps), the best-on-validation weights
    (``params.msgpack`` + ``config.json``), ``curves.png`` and a resumable ``checkpoint.msgpack``
    (a killed run continues from its last evaluation). Returns the final summary."""
    train.check("training data")
    val.check("validation data")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    init, apply = make_completion(config)
    opt, sched = checkpoints.optimizer(tc)
    params = init(jax.random.key(tc.seed))
    state = dict(params=params, opt=opt.init(params), step=0, best=np.inf, best_step=-1)
    history = folder / "history.jsonl"
    state = checkpoints.open_run(folder, config, tc, state, f"completion[{config.kind}]")

    @jax.jit
    def step_fn(params, opt_state, x, t):
        def loss_fn(p):
            coarse, fine = apply(p, x)
            return jnp.mean(chamfer(coarse, t) + chamfer(fine, t))

        loss, grads = jax.value_and_grad(loss_fn)(params)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    rng = np.random.default_rng([tc.seed, state["step"]])
    params, opt_state = state["params"], state["opt"]
    losses, t0 = [], time.time()
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=tc.steps, initial=state["step"], desc=f"completion[{config.kind}]")
    for step in range(state["step"] + 1, tc.steps + 1):
        x, t = sample_batch(train, rng, tc.batch, config.n_input)
        params, opt_state, loss = step_fn(params, opt_state, x, t)
        losses.append(loss)
        if bar is not None:
            bar.update(1)
        if step % tc.eval_every == 0 or step == tc.steps:
            train_loss = float(np.mean(jax.device_get(losses)))
            if not np.isfinite(train_loss):
                raise FloatingPointError(
                    f"completion[{config.kind}]: loss {train_loss} at step {step}"
                )
            losses = []
            metrics = evaluate(apply, params, val, config, tc.tol)
            row = dict(step=step, train_loss_mm=1e3 * train_loss, lr=float(sched(step)),
                       seconds=round(time.time() - t0, 1),
                       **{f"val_{k}": v for k, v in metrics.items()})  # fmt: skip
            with open(history, "a") as f:
                f.write(json.dumps(row) + "\n")
            if bar is not None:
                bar.set_postfix(train=f"{row['train_loss_mm']:.2f}",
                                val=f"{metrics['chamfer_mm']:.2f}")  # fmt: skip
            best, best_step = float(state["best"]), int(state["best_step"])
            if metrics["chamfer_mm"] < best:
                best, best_step = metrics["chamfer_mm"], step
                save_completion(folder, config, params, step=step, val=metrics,
                                train=dataclasses.asdict(tc))  # fmt: skip
            state = checkpoints.save_checkpoint(folder, params, opt_state, step, best, best_step)
    if bar is not None:
        bar.close()
    plot_history(history, folder / "curves.png", config.kind)
    rows = [json.loads(x) for x in history.read_text().splitlines() if x.strip()]
    return dict(kind=config.kind, best_step=int(state["best_step"]), best_val_chamfer_mm=float(state["best"]),
                last=rows[-1] if rows else None)  # fmt: skip


def plot_history(history, png, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [json.loads(x) for x in Path(history).read_text().splitlines() if x.strip()]
    if not rows:
        return
    s = [r["step"] for r in rows]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].plot(s, [r["train_loss_mm"] for r in rows], label="train (coarse + fine)")
    ax[0].plot(s, [r["val_chamfer_mm"] for r in rows], "--o", ms=3, label="validation (fine)")
    ax[0].set_ylabel("Chamfer distance (mm)")
    for k in [
        k for k in rows[-1] if k.startswith(("val_coverage", "val_observed", "val_accuracy"))
    ]:
        ax[1].plot(s, [r[k] for r in rows], label=k[4:])
    ax[1].set_ylabel("share within tolerance")
    for a in ax:
        a.set_xlabel("step")
        a.legend(fontsize=8)
    fig.suptitle(f"shape completion: {title}")
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def load_nets(folder_or_nets) -> dict:
    """kind -> (config, params) of both networks, from a folder holding ``object/`` and
    ``support/`` (a dict of them is returned as it is)."""
    if isinstance(folder_or_nets, dict):
        return folder_or_nets
    return {k: load_completion(Path(folder_or_nets) / k)[:2] for k in KINDS}


def predict_points(folder_or_nets, object_points, support_points, eyes=None, seed: int = 0):
    """(predicted object points [M, 3], predicted support points [M', 3]), each in its cloud's
    frame (:func:`load_nets`' networks). Each network sees a fixed random ``n_input`` subset
    (``seed``) of its observed cloud. With ``eyes`` = (object camera, support camera) the points
    each camera would have seen are dropped (:func:`carve`), so M, M' <= ``n_output``. Raises
    ``ValueError`` for an empty or non-finite cloud."""
    nets = load_nets(folder_or_nets)
    out = []
    for i, (kind, pts) in enumerate((("object", object_points), ("support", support_points))):
        pts = np.asarray(pts, np.float32)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
            raise ValueError(f"the {kind} cloud must be [N>0, 3], got {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise ValueError(f"the {kind} cloud holds NaN or inf")
        config, params = nets[kind]
        rng = np.random.default_rng(seed)
        sub = pts[rng.choice(len(pts), config.n_input, replace=len(pts) < config.n_input)]
        pred = np.asarray(_complete_cached(config)(params, sub[None]))[0]
        if eyes is not None:
            pred = carve(pred, pts, eyes[i])[0]
        out.append(pred)
    return tuple(out)


def predict_points_many(folder_or_nets, object_clouds, support_clouds, eyes=None,
                        seed: int = 0, chunk: int = 256, workers: int = 8) -> list[tuple]:  # fmt: skip
    """:func:`predict_points` for P pairs at once: object_clouds [P, N, 3], support_clouds
    [P, N', 3], eyes None or P (object camera, support camera) -> P (predicted object,
    predicted support). Each pair's network input is the same fixed subset as
    :func:`predict_points`' (``seed``), the forward passes run ``chunk`` pairs at a time and
    the carving in ``workers`` threads: the same points as one pair at a time, up to float
    rounding of the batched forward pass."""
    from concurrent.futures import ThreadPoolExecutor

    nets = load_nets(folder_or_nets)
    clouds = {"object": np.asarray(object_clouds, np.float32),
              "support": np.asarray(support_clouds, np.float32)}  # fmt: skip
    predicted = {}
    for kind, pts in clouds.items():
        if pts.ndim != 3 or pts.shape[-1] != 3 or pts.shape[1] == 0:
            raise ValueError(f"the {kind} clouds must be [P, N>0, 3], got {pts.shape}")
        bad = np.flatnonzero(~np.all(np.isfinite(pts), axis=(1, 2)))
        if len(bad):
            raise ValueError(f"the {kind} clouds of pairs {bad[:5].tolist()} hold NaN or inf")
        config, params = nets[kind]
        rng = np.random.default_rng(seed)
        pick = rng.choice(pts.shape[1], config.n_input, replace=pts.shape[1] < config.n_input)
        fn = _complete_cached(config)
        parts = []
        for i in range(0, len(pts), chunk):
            sub = pts[i : i + chunk, pick]
            n = len(sub)
            if n < chunk and len(pts) > chunk:  # one compiled shape
                sub = np.concatenate([sub, np.repeat(sub[-1:], chunk - n, axis=0)])
            parts.append(np.asarray(fn(params, sub))[:n])
        predicted[kind] = np.concatenate(parts)
    if eyes is None:
        return list(zip(predicted["object"], predicted["support"]))

    def carve_pair(i):
        return tuple(
            carve(predicted[kind][i], clouds[kind][i], eyes[i][j])[0]
            for j, kind in enumerate(KINDS)
        )

    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(carve_pair, range(len(clouds["object"]))))


def completed_observed_rows(n: int, seed: int = 0) -> np.ndarray:
    """The observed rows :func:`completed_cloud` keeps of an N-row cloud, in its first N - N // 2
    rows (so that per-point arrays, e.g. normals, can follow them)."""
    from omnihang_jax.collision import subsample_indices

    return subsample_indices(n, n - n // 2, seed)


def completed_cloud(observed, predicted, seed: int = 0) -> np.ndarray:
    """The input of an NCE trained on completed clouds (``NCEConfig.input_clouds``): as many
    points as ``observed`` [N, 3], the observed rows :func:`completed_observed_rows` followed by
    a fixed subset of N // 2 predicted points (with replacement where fewer; the other observed
    rows instead when carving left none). The same function builds the training clouds
    (``experiments.train_collision --completion``) and the planner's (``experiments.eval_paths``),
    so both see the same mixture."""
    from omnihang_jax.collision import subsample_indices

    obs = np.asarray(observed, np.float32)
    pred = np.asarray(predicted, np.float32).reshape(-1, 3)
    if obs.ndim != 2 or obs.shape[1] != 3 or len(obs) < 2:
        raise ValueError(f"the observed cloud must be [N>1, 3], got {obs.shape}")
    rows = completed_observed_rows(len(obs), seed)
    half = len(obs) // 2
    if len(pred) == 0:
        return np.concatenate([obs[rows], np.delete(obs, rows, axis=0)])
    return np.concatenate([obs[rows], pred[subsample_indices(len(pred), half, seed + 1)]])


def clearance_clouds(object_points, support_points, predicted_object, predicted_support,
                     n_object: int, seed: int = 0):  # fmt: skip
    """(object cloud, support cloud) of a clearance test on completed shapes: a fixed subset
    (``seed``) of ``n_object`` observed object points plus as many of the predicted ones (none
    when carving left none), and the whole observed support cloud plus its predicted points.
    Used alike by ``experiments.eval_paths --completion`` and the ``hang`` command."""
    from omnihang_jax.collision import subsample_cloud

    parts = [subsample_cloud(object_points, n_object, seed)]
    if len(predicted_object):
        parts.append(subsample_cloud(predicted_object, n_object, seed))
    support = [
        np.asarray(support_points, float),
        np.asarray(predicted_support, float).reshape(-1, 3),
    ]
    return np.concatenate(parts).astype(float), np.concatenate(support)


_COMPLETE: dict = {}


def _complete_cached(config: CompletionConfig):
    if config not in _COMPLETE:
        _COMPLETE[config] = complete_fn(config)
    return _COMPLETE[config]


def carve(predicted, observed, eye, behind: float = 0.002, cell_factor: float = 1.5):
    """Predicted points [M, 3] that the camera at ``eye`` could not have seen, the rest dropped
    (free-space carving; numpy, host side). The observed cloud [N, 3] (same frame as ``eye``)
    becomes a depth map over viewing directions, cells ``cell_factor`` x the cloud's median
    angular spacing, each cell the nearest depth within its 3 x 3 neighbourhood. A predicted
    point is dropped when its direction falls in a cell where the camera saw nothing (the ray
    went through empty space) or when it lies more than ``behind`` in front of the observed
    surface there: either way the camera would have seen it. Kept: points behind the observed
    surface (its hidden back). Returns (kept points [K, 3], kept mask [M])."""
    pred = np.asarray(predicted, float)
    keep = depth_map(observed, eye, cell_factor)(pred) >= -behind
    return pred[keep], keep


def depth_map(observed, eye, cell_factor: float = 1.5):
    """The observed cloud [N, 3] seen from ``eye`` (same frame) as a depth map over viewing
    directions (:func:`carve`'s): cells ``cell_factor`` x the cloud's median angular spacing,
    each cell the nearest depth within its 3 x 3 neighbourhood. Returns ``behind(points [M, 3])
    -> [M]``: how far each point lies behind the observed surface along its ray from the eye
    (m; negative in front of it), ``-inf`` where the camera saw nothing in that direction."""
    from scipy.spatial import cKDTree

    # distinct points: a cloud drawn with replacement repeats points, which must change
    # neither the viewing axes nor the cell size (a median spacing of 0 would make every cell
    # empty; twenty-eighth session: 2 of 81 held-out object clouds)
    obs = np.unique(np.asarray(observed, float), axis=0)
    if len(obs) < 2:
        raise ValueError("carving needs an observed cloud of two distinct points or more")
    eye = np.asarray(eye, float).reshape(3)
    fwd = (obs - eye).mean(axis=0)
    fwd /= np.linalg.norm(fwd)
    up = np.array([0.0, 0.0, 1.0]) if abs(fwd[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    axes = np.stack([right, np.cross(right, fwd), fwd])

    def project(points):
        v = (points - eye) @ axes.T
        ahead = v[:, 2] > 1e-6
        ab = v[:, :2] / np.maximum(v[:, 2:3], 1e-6)
        return ab, np.linalg.norm(v, axis=1), ahead

    ab, depth, _ = project(obs)
    spacing = cKDTree(ab).query(ab, k=2)[0][:, 1]
    if not np.any(spacing > 0):
        raise ValueError("carving needs observed points on two viewing directions or more")
    cell = cell_factor * float(np.median(spacing[spacing > 0]))
    ij = np.floor(ab / cell).astype(np.int64)
    lo = ij.min(axis=0) - 2
    shape = tuple(ij.max(axis=0) - lo + 3)
    grid = np.full(shape, np.inf)
    np.minimum.at(grid, tuple((ij - lo).T), depth)
    near = grid.copy()
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            near = np.minimum(near, np.roll(np.roll(grid, di, 0), dj, 1))

    def behind(points):
        pts = np.asarray(points, float).reshape(-1, 3)
        pab, pdepth, ahead = project(pts)
        pij = np.floor(pab / cell).astype(np.int64) - lo
        inside = ahead & np.all((pij >= 0) & (pij < np.array(shape)), axis=1)
        front = np.full(len(pts), np.inf)
        pij = np.where(inside[:, None], pij, 0)
        front[inside] = near[pij[inside, 0], pij[inside, 1]]
        return np.where(inside & np.isfinite(front), pdepth - front, -np.inf)

    return behind
