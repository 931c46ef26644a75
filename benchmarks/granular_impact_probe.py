"""Impact probe of a particle GNS: from the true history, does one step give the impulse of
an impact?

    .venv/bin/python benchmarks/granular_impact_probe.py --model gns_general \
        --data data/granular_valid.h5 [--n 24] [--threshold-g 5] [--out granular_impact_probe]

For every trajectory and every frame t (teacher forcing: the model's input is the MPM's
nodes at frames t-C-1 .. t-1, its own node reduction and frame stride), the model makes one
step; its node acceleration a = x_t - 2 x_{t-1} + x_{t-2} (m/frame^2) is compared with the
MPM's. A frame is an **impact frame** when the RMS over nodes of the MPM's |a| exceeds
``--threshold-g`` times g (free fall is 1 g, rest 0, the flows of a collapse < 1 g; a mass
striking a wall or an obstacle 8-40 g for one to three frames). Per case:

* ``captured``: sum over impact frames and nodes of a_pred . a_ref / sum of |a_ref|^2, the
  share of the impacts' acceleration the model reproduces along the truth (1 is exact, 0 no
  impact at all);
* ``impact_rel_rms``: sqrt(sum |a_pred - a_ref|^2 / sum |a_ref|^2) over impact frames;
* ``other_rms_g``: RMS of |a_pred - a_ref| over the other frames, in g.

A rollout error born in the impacts shows here as ``captured`` far below 1 while the other
frames are fitted. Accuracy only (the protocol records the load, never refuses). Writes
``benchmarks/results/<out>.json``.
"""
from __future__ import annotations

import argparse

import numpy as np
import protocol

G = 9.81  # m/s^2


def impact_summary(a_pred: np.ndarray, a_ref: np.ndarray, g_frame: float,
                   threshold_g: float) -> dict:
    """Impact scores of teacher-forced accelerations ``a_pred``, ``a_ref`` (M, N, d) in
    m/frame^2 (M frames, N nodes); ``g_frame`` is g in m/frame^2. Keys: ``impact_frames``
    (count), ``captured`` and ``impact_rel_rms`` (None without impact frames),
    ``other_rms_g`` (None without other frames), ``peak_ref_rms_g``."""
    a_pred, a_ref = np.asarray(a_pred, float), np.asarray(a_ref, float)
    if a_pred.shape != a_ref.shape or a_ref.ndim != 3:
        raise ValueError(f"a_pred {a_pred.shape} and a_ref {a_ref.shape} must both be (M, N, d)")
    rms_ref = np.sqrt((a_ref ** 2).sum(-1).mean(-1)) / g_frame  # (M,) in g
    hit = rms_ref > threshold_g
    out: dict = dict(impact_frames=int(hit.sum()), captured=None, impact_rel_rms=None,
                     other_rms_g=None, peak_ref_rms_g=float(rms_ref.max(initial=0.0)))
    if hit.any():
        p, r = a_pred[hit], a_ref[hit]
        norm = float((r ** 2).sum())
        out["captured"] = float((p * r).sum()) / norm
        out["impact_rel_rms"] = float(np.sqrt(((p - r) ** 2).sum() / norm))
    if (~hit).any():
        e = ((a_pred[~hit] - a_ref[~hit]) ** 2).sum(-1)
        out["other_rms_g"] = float(np.sqrt(e.mean())) / g_frame
    return out


def accelerations(gns0, network, ref, stride: int = 1):
    """(a_pred, a_ref) (M, N, d) m/frame^2 at every ``stride``-th frame from C + 1 on: one
    model step from the reference's own history
    (:func:`diffgns.graph.evaluate.teacher_forced`), and the reference's own step. The one
    place this script calls the simulator."""
    from diffgns.graph.evaluate import teacher_forced

    p = np.asarray(ref.positions)
    frames = np.arange(gns0.config.history + 1, p.shape[0], stride)
    _, x = teacher_forced(gns0, network, ref, frames)
    return x - 2 * p[frames - 1] + p[frames - 2], p[frames] - 2 * p[frames - 1] + p[frames - 2]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", required=True, help="model folder or shipped name")
    ap.add_argument("--data", required=True, help="dataset (.h5 with families)")
    ap.add_argument("--n", type=int, default=None, help="first n trajectories only")
    ap.add_argument("--threshold-g", type=float, default=5.0,
                    help="impact frame: RMS node acceleration of the MPM above this many g")
    ap.add_argument("--stride", type=int, default=1, help="probe every stride-th frame")
    ap.add_argument("--out", default="granular_impact_probe.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    if args.threshold_g <= 0 or args.stride < 1:
        ap.error("--threshold-g must be > 0 and --stride >= 1")
    run = protocol.start(args, "granular_impact_probe", timed=False)

    from diffgns.graph.data import load_trajectories
    from diffgns.graph.train_loop import load_model
    from diffgns.io.families_data import read_families

    gns0, network, info = load_model(args.model)
    refs, _ = load_trajectories(args.data, int(info.get("factor", 1)),
                                int(info.get("frame_stride", 1)))
    families = list(read_families(args.data).values())
    refs, families = refs[: args.n], families[: args.n]
    rows = []
    for i, (ref, fam) in enumerate(zip(refs, families)):
        a_pred, a_ref = accelerations(gns0, network, ref, args.stride)
        row = dict(case=i, family=fam,
                   **impact_summary(a_pred, a_ref, G * ref.frame_dt ** 2, args.threshold_g))
        rows.append(row)
        run.print(f"case {i:3d} {fam:10s} impact frames {row['impact_frames']:3d} "
                  f"(peak {row['peak_ref_rms_g']:5.1f} g): captured {_fmt(row['captured'])}, "
                  f"rel RMS {_fmt(row['impact_rel_rms'])}; other frames RMS "
                  f"{_fmt(row['other_rms_g'])} g")
    table = {fam: family_means([r for r in rows if r["family"] == fam])
             for fam in dict.fromkeys(families)}
    table["all"] = family_means(rows)
    for fam, t in table.items():
        run.print(f"{fam:10s} cases with impacts {t['cases_with_impacts']:2d}: captured "
                  f"{_fmt(t['captured_mean'])}, rel RMS {_fmt(t['impact_rel_rms_mean'])}; "
                  f"other frames RMS {_fmt(t['other_rms_g_mean'])} g")
    path = run.finish(args.out, dict(model=str(args.model), data=str(args.data),
                                     threshold_g=args.threshold_g, stride=args.stride,
                                     rows=rows, table=table))
    run.print(f"wrote {path}")


def family_means(rows: list[dict]) -> dict:
    """Means of a family's rows: ``captured`` and ``impact_rel_rms`` over the cases with
    impact frames, ``other_rms_g`` over all (None where no case has one)."""
    def mean(key):
        v = [r[key] for r in rows if r[key] is not None]
        return float(np.mean(v)) if v else None
    return dict(cases=len(rows),
                cases_with_impacts=sum(r["captured"] is not None for r in rows),
                captured_mean=mean("captured"), impact_rel_rms_mean=mean("impact_rel_rms"),
                other_rms_g_mean=mean("other_rms_g"))


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.3f}"


if __name__ == "__main__":
    main()
