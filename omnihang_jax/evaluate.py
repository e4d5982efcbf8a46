"""The evaluation protocol: when a predicted pose counts as hanging (paper, "hanging success").

The protocol of the original code (facts file, "Evaluation") on our kernels:

* A predicted pose is loaded at rest and simulated 100 steps of 1/100 s (1 s) under gravity
  with the scene's physics (0.5 kg, friction 0.5: the settings the dataset was labelled with):
  ``StabilityConfig.duration = 1.0``.
* Failure if the initial penetration exceeds 3 mm (status PENETRATING), if the bounding boxes
  of object and support stop overlapping or the object touches the ground (FALLEN), or if the
  simulation diverges (DIVERGED: a non-finite state is a failure, never a NaN figure). Success
  = STABLE. A world that has rested for two consecutive 0.1 s checks stops early; an object at
  rest under gravity does not start moving again, so this only saves time.
* One answer per pair is simulated; a figure is the mean over object categories of the
  per-category success (%), over the held-out ("test") pairs with at least one ground-truth
  stable pose. Which answer each figure reads: :mod:`omnihang_jax.where_eval`.

Frames: the object cloud lives in the OBJECT frame (origin at its bounding-box centre), the
support cloud in the SUPPORT frame, the scene's world frame. Predicted poses are the object
frame in the support frame (xyz + quaternion wxyz), exactly the ``poses [B, 7]`` that
``sim.kernels.stability`` takes.
"""

from __future__ import annotations

__all__ = ["PAPER_SUCCESS", "protocol_stability"]

# The paper's held-out figures, mean over the 11 categories (facts file, "Headline results").
PAPER_SUCCESS = {"stage1": 36.0, "stage1_2": 34.2, "stage1_3": 56.2, "all_stages": 68.3}


def protocol_stability():
    """The ``sim.kernels.StabilityConfig`` of the evaluation protocol (module docstring)."""
    from sim import kernels

    return kernels.StabilityConfig(
        duration=1.0,  # s: 100 steps of 1/100 s (original evaluation)
        max_penetration=0.003,  # m: a prediction penetrating > 3 mm fails at once (original)
    )
