"""Predict hanging poses with trained Stage 1 + Stage 2 networks.

    python -m experiments.predict_where --model weights/where_small_paper --data synthetic --pairs 4
    python -m experiments.predict_where --model weights/where_small_paper --data datasets/paper/derived --split test

Loads MODEL/stage1 and MODEL/stage2b (config.json + latest checkpoint), predicts
--proposals poses per pair, and writes OUT (default out/predict_where/predictions.json;
never into the model folder unless asked): per pair the
Stage-1 and Stage-2 poses (xyz metres + quaternion wxyz, object frame in support frame; Stage 1
released ``--stage1-lift`` above the network's pose and Stage 2 with the answer's clearance,
``--stage2-clearance``), each stage's answer among them (``--select``: the least penetrating
of the observed support, as eval_where evaluates it; the Stages 1+2 answer released
``--stage2-lift`` higher), the
chosen contact correspondences and, where ground truth is known, the distance from each
predicted position to the nearest stable pose.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os

import jax
import numpy as np

from experiments import _cli
from omnihang_jax import data, evaluate, predict, stage1, stage2, stage3, train


def position_errors(poses7: np.ndarray, sample: data.HangSample) -> np.ndarray:
    """poses7 [K, 7] -> [K] distance (m) from each position to the nearest valid stable pose."""
    gt = np.asarray(sample.stable_poses)[np.asarray(sample.pose_mask, bool), :3]
    return np.linalg.norm(poses7[:, None, :3] - gt[None], axis=-1).min(1)


parse_view_set = stage3.parse_view_set  # (moved to omnihang_jax.stage3, thirty-second session)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model", required=True, help="folder written by train_where")
    parser.add_argument("--data", default="synthetic", help="'synthetic' or a dataset directory")
    parser.add_argument("--split", default="test", help="dataset split for a directory")
    parser.add_argument("--pairs", type=int, default=4, help="number of pairs to predict")
    parser.add_argument(
        "--proposals", type=int, default=None, help="poses per pair (default: Stage-1 eval Z)"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--stage1-lift", type=float, default=stage1.ANSWER_LIFT, metavar="M",
        help="the Stage-1 poses released M metres above the network's pose (+z of the support "
        "frame; default stage1.ANSWER_LIFT, the Stage-1 answer; 0: the network's pose). Stage 2 "
        "starts from the network's pose either way",
    )  # fmt: skip
    parser.add_argument(
        "--select", choices=evaluate.SELECTS, default=evaluate.ANSWER_SELECT,
        help="which proposal of each stage is the pair's answer (stage1_answer / stage2_answer): "
        "the one whose object cloud least enters the observed support cloud (default "
        "evaluate.ANSWER_SELECT, as eval_where), or the first drawn",
    )  # fmt: skip
    parser.add_argument(
        "--stage2-clearance", type=float, default=stage2.ANSWER_CLEARANCE, metavar="M",
        help="the Stage-2 poses' clearance in metres along the observed support normal (default "
        "stage2.ANSWER_CLEARANCE, the Stages 1+2 answer; 0: the paper's); Stage 3 (--value) "
        "starts from Stage 2 without it, as the evaluated pipeline",
    )  # fmt: skip
    parser.add_argument(
        "--stage2-lift", type=float, default=stage2.ANSWER_LIFT, metavar="M",
        help="the Stages 1+2 answer (stage2_answer) released M metres above the chosen pose, "
        "after the clearance and the selection (default stage2.ANSWER_LIFT; 0: none)",
    )  # fmt: skip
    parser.add_argument(
        "--value",
        default=None,
        metavar="DIR",
        help="also run Stage 3 (CEM on this value function, e.g. weights/value_s16_hardneg): "
        "the whole pipeline as one jitted call; adds stage3_poses, stage3_scores, answer",
    )
    parser.add_argument(
        "--views", type=int, default=None, metavar="N",
        help="with --value: run CEM and the ranking on N evenly spaced subsamples of the clouds "
        "(shifts 0, 1/N, ...) and answer with the best of all their candidates "
        "(stage3.PipelineConfig.views; default: the answer pipeline's own "
        f"{','.join(f'{j}/{t}' for j, t in stage3.ANSWER_PIPELINE.views)}: held-out 82.90 %% "
        "against 81.88 for 0/1,1/2 over three CEM keys, thirty-second session)",
    )  # fmt: skip
    parser.add_argument(
        "--view-set", default=None, metavar="J/T,...",
        help="with --value: the subsamples themselves, e.g. 0/1,1/2,3/4 (subset J of T; "
        "overrides --views). The default since the thirty-third session is 0/1,1/2,3/4: 97.1 ms "
        "a pair against 80.5 for 0/1,1/2 on one H200 (docs/stage3.md)",
    )  # fmt: skip
    parser.add_argument(
        "--out",
        default="out/predict_where/predictions.json",
        help="output JSON (default out/predict_where/predictions.json)",
    )
    args = parser.parse_args(argv)
    if args.views is not None and args.views < 1:
        parser.error("--views must be >= 1")
    views = stage3.ANSWER_PIPELINE.views
    if args.views is not None:
        views = tuple((j, args.views) for j in range(args.views))
    if args.view_set is not None:
        try:
            views = parse_view_set(args.view_set)
        except ValueError as e:
            parser.error(f"--view-set: {e}")

    predictor = predict.load_predictor(
        args.model, seed=args.seed, stage2_overrides={"clearance": args.stage2_clearance}
    )
    config, _, _ = train.restore_stage(os.path.join(args.model, "stage1"))
    if args.data == "synthetic":
        batch = data.synthetic_batch(
            jax.random.key(args.seed + 777), args.pairs, config.num_object_points
        )
    else:
        dataset = data.load_hang_dataset(args.data, split=args.split)
        batch = dataset.sample_batch(np.random.default_rng(args.seed), args.pairs)
    out = predictor(
        batch.object_points,
        batch.support_points,
        num_proposals=args.proposals,
        support_normals=batch.support_normals,
    )
    stage1_poses = evaluate.lift_poses(out.stage1_poses, args.stage1_lift)
    samples = data.unstack(batch)
    # the answers: each stage's K proposals ranked as eval_where ranks them (after the lift)
    answer1 = np.zeros(len(samples), int)
    answer2 = np.zeros(len(samples), int)
    if args.select == "penetration":
        for i, sample in enumerate(samples):
            answer1[i] = evaluate.penetration_order(sample, stage1_poses[i])[0]
            answer2[i] = evaluate.penetration_order(sample, out.stage2_poses[i])[0]
    stage3_out = None
    if args.value:
        k = args.proposals or predictor.stage1_config.num_eval_samples
        hang, params = predict.load_hang_pipeline(
            args.model, args.value,
            dataclasses.replace(stage3.ANSWER_PIPELINE, num_proposals=k,
                                views=views),
        )  # fmt: skip
        clouds = stage3.PairClouds(
            batch.object_points, batch.object_normals, batch.support_points, batch.support_normals
        )
        stage3_out = hang(params, jax.random.key(args.seed), clouds)

    records = []
    for i, sample in enumerate(samples):
        records.append(
            {
                "pair": i,
                "stage1_poses": stage1_poses[i].tolist(),
                "stage2_poses": out.stage2_poses[i].tolist(),
                "stage1_answer": stage1_poses[i][answer1[i]].tolist(),
                "stage1_answer_index": int(answer1[i]),
                "stage2_answer": evaluate.lift_poses(
                    out.stage2_poses[i][answer2[i]], args.stage2_lift
                ).tolist(),
                "stage2_answer_index": int(answer2[i]),
                "object_indices": out.object_indices[i].tolist(),
                "support_indices": out.support_indices[i].tolist(),
                "pair_probability": out.probability[i].tolist(),
                "pair_weight": out.weight[i].tolist(),
                "stage1_position_error_m": position_errors(stage1_poses[i], sample).tolist(),
                "stage2_position_error_m": position_errors(out.stage2_poses[i], sample).tolist(),
            }
        )
        if stage3_out is not None:
            refined = np.asarray(stage3_out.refined["stage2"][i])
            records[-1].update(
                stage3_poses=refined.tolist(),
                stage3_scores=np.asarray(stage3_out.scores["stage2"][i]).tolist(),
                answer=np.asarray(stage3_out.pose[i]).tolist(),
                stage3_position_error_m=position_errors(refined, sample).tolist(),
            )
    summary = {
        "model": args.model,
        "data": args.data,
        "pairs": len(records),
        "stage1_lift_m": args.stage1_lift,
        "select": args.select,
        "stage2_clearance_m": args.stage2_clearance,
        "stage2_lift_m": args.stage2_lift,
        "views": [f"{j}/{t}" for j, t in views] if args.value else None,
        "mean_stage1_position_error_m": float(
            np.mean([r["stage1_position_error_m"] for r in records])
        ),
        "mean_stage2_position_error_m": float(
            np.mean([r["stage2_position_error_m"] for r in records])
        ),
    }
    path = args.out
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump({"summary": summary, "pairs": records}, f, indent=1)
    print(json.dumps(summary, indent=1))
    print(f"wrote {path}")
    return summary


if __name__ == "__main__":
    _cli.run(main)
