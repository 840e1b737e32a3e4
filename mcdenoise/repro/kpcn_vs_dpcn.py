"""KPCN vs DPCN (Bako et al. 2017, Sec. 7 and Fig. 9): kernel prediction converges faster.

Both networks are the same convolutional body on the same diffuse/specular inputs; DPCN's last
layer outputs the (transformed) colour, KPCN's a 21x21 (here: the small preset's 9x9) kernel. The
paper trains both and plots validation L1 against hours: "the KPCN system converges 5-6x faster"
to "a similar error". At equal steps (not hours) we record validation L1 of the recombined image
and ask how many steps KPCN needs to reach DPCN's final value.
"""

from __future__ import annotations

from typing import Any

from mcdenoise.repro.common import Experiment, Variant

__all__ = ["EXPERIMENT", "judge"]


def steps_to_reach(curve: list[dict[str, float]], metric: str, level: float) -> int | None:
    """First validation step whose ``metric`` is at or below ``level``; None if never."""
    return next((int(p["step"]) for p in curve if p[metric] <= level), None)


def judge(result: dict[str, Any]) -> tuple[str, str]:
    m = result["metric"]
    k, d = result["variants"]["kpcn"], result["variants"]["dpcn"]
    kf, df = k["curve"][-1][m], d["curve"][-1][m]
    reach = steps_to_reach(k["curve"], m, df)
    steps = result["steps"]
    if reach is None:
        return "disagrees", (f"KPCN ends at validation L1 {kf:.4g}, above DPCN's final {df:.4g}: at this budget "
                             f"kernel prediction did not converge faster.")
    speed = steps / reach
    ahead = sum(kp[m] < dp[m] for kp, dp in zip(k["curve"], d["curve"]))
    # Validation points bracket the crossing: KPCN got there after the point before `reach`.
    before = max((int(p["step"]) for p in k["curve"] if int(p["step"]) < reach), default=0)
    if before == 0:
        how = (f"at least {speed:.1f}x sooner (paper: 5-6x in training hours; a lower bound set by the first "
               f"validation point, where KPCN was already below it: more frequent validation would measure it)")
    else:
        how = (f"{speed:.1f}-{steps / before:.1f}x sooner (paper: 5-6x in training hours; it crossed between "
               f"validation steps {before} and {reach})")
    text = (f"KPCN is at DPCN's final validation L1 ({df:.4g}) or below by step {reach} of {steps}, "
            f"{how}; it ends at {kf:.4g} "
            f"({(1 - kf / df) * 100:+.0f}% lower error) and is ahead at {ahead} of {len(k['curve'])} validation points.")
    if reach < steps:
        return "agrees", text
    return "partly", text + " It gets there only at the last step, so it is not clearly faster."


EXPERIMENT = Experiment(
    name="kpcn-vs-dpcn",
    title="KPCN converges faster than DPCN (Bako et al. 2017, Fig. 9)",
    claim=("Bako, Vogels et al. 2017, Sec. 7 and Fig. 9: \"Although both approaches converge to a similar error on "
           "the Cars 3 validation set, the KPCN system converges 5-6x faster\"; DPCN's convergence \"is slower with "
           "considerably higher variance, on average requiring 5-6x longer to reach the same loss value\" "
           "(validation L1 against training hours, diffuse and specular networks; KPCN stopped after 50 hours)."),
    variants=(Variant("kpcn", "KPCN", "kpcn"), Variant("dpcn", "DPCN", "dpcn")),
    metric="l1",
    # Sized from 12-step timings with one thread at load ~6: KPCN 0.21 s/step, DPCN 0.10 s/step
    # (~8 min for both plus validations); not yet timed end to end (see docs/RESULTS.md).
    steps=1500,
    judge=judge,
    validations=8,
    notes=("Equal steps, not equal hours: KPCN's kernel costs a little more per step. Both use the engine's KPCN "
           "schedule (per-branch L1 for the first 80% of the steps, then the recombined image), and validation L1 "
           "is measured on the recombined image, not per branch as in the paper's plot. The networks share the "
           "body; only the last layer differs (kernel weights vs colour), hence the parameter counts."),
)
