"""Per-iteration curves of students' DAgger runs from their metrics.json: the cross-entropy to the teacher's
distribution on each iteration's new frames before the student was cloned on them (a held-out loss: those frames
were never trained on) and after, and the rollouts' success rate, against the pool's size.
Run from the repository root:
  .venv/bin/python docs/notes/scripts/dagger_iterations_figure.py OUT.png LABEL=POLICY_DIR [LABEL=POLICY_DIR ...]
(docs/results.md, the paper's MLP head and the amount of data)"""
import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

out, runs = Path(sys.argv[1]), [a.split("=", 1) for a in sys.argv[2:]]
fig, (ax_ce, ax_sr) = plt.subplots(1, 2, figsize=(10, 3.8))
for label, run in runs:
    its = json.loads((Path(run) / "metrics.json").read_text())["dagger"]
    pool = [it["aggregate_frames"] / 1000 for it in its]
    line, = ax_ce.plot(pool, [it["soft_ce_new_before"] for it in its], "o-", label=f"{label}: before (held out)")
    ax_ce.plot(pool, [it["soft_ce_new_after"] for it in its], "s--", color=line.get_color(),
               label=f"{label}: after cloning")
    ax_sr.plot(pool, [it["rollout_success_rate"] for it in its], "o-", color=line.get_color(), label=label)
    for it, x in zip(its, pool, strict=True):
        ax_sr.annotate(f"β={it['beta']:.2g}", (x, it["rollout_success_rate"]), fontsize=6,
                       textcoords="offset points", xytext=(2, 4))
ax_ce.set(xlabel="DAgger pool [k frames]", ylabel="cross-entropy to the teacher [nats]",
          title="each iteration's new frames")
ax_sr.set(xlabel="DAgger pool [k frames]", ylabel="rollout success rate", title="the iteration's rollouts (β-mixed)",
          ylim=(0, 1))
ax_ce.legend(fontsize=7)
ax_sr.legend(fontsize=7)
fig.tight_layout()
fig.savefig(out, dpi=120)
print(out)
