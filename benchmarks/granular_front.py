"""What accuracy costs in time for the general granular GNS: every timed model on one plot.

Draws no new measurement. It pairs, per model, two records of ``granular_heldout.py`` on the
validation set: the accuracy run over all its cases and the timed run (``--n 8 --timed 3``,
quiet machine, both thread modes where recorded), and plots the mean final position error
(per case: error / mean displacement) against the median speed-up over the stable-dt MPM,
with issue 21's targets (error <= 0.05, speed-up >= 10x) as the corner to reach.

    python benchmarks/granular_front.py --out granular_front

Every point's files, date, load at start, commit and command are copied into the JSON. A
timed record that is not protocol-valid (run above the load limit) is refused, as is a pair
whose two records are on different datasets: a figure beside a training is not a figure.
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import protocol

ERROR = "final_position_error_rel_displacement"
TARGET_ERROR, TARGET_SPEEDUP = 0.05, 10.0
LABEL_OFFSETS = ((5, 5), (5, -9), (-5, 5), (-5, -9))  # points, cycled along the sorted points

# label -> (accuracy record, timed record), all under benchmarks/results/.
DEFAULT_PAIRS = {
    "gns_general": ("granular_valid_general_fs_soup4u8.json",
                    "granular_valid_gns_general_timed_2026-12-07b.json"),
    "soup4": ("granular_valid_general_fs_soup4.json", "granular_valid_general_fs_soup4_timed.json"),
    "r1b": ("granular_valid_general_fs_r1b.json", "granular_valid_general_fs_r1b_timed.json"),
    "r2 (stride 2)": ("granular_valid_general_fs_r2.json",
                      "granular_valid_general_fs_r2_timed.json"),
    "r4 (stride 4)": ("granular_valid_general_fs_r4.json",
                      "granular_valid_general_fs_r4_timed.json"),
    "a1 (4 per node)": ("granular_valid_general_cg4_a1.json",
                        "granular_valid_general_cg4_a1_timed.json"),
    "c3b (3 steps)": ("granular_valid_general_fs_c3b.json",
                      "granular_valid_c3b_timed_2026-12-07.json"),
    "c32b (latent 32)": ("granular_valid_general_fs_c32b.json",
                         "granular_valid_c32b_timed_2026-12-07.json"),
    "c32m3 (latent 32, 3 steps)": ("granular_valid_general_fs_c32m3.json",
                                   "granular_valid_c32m3_timed_2026-12-07.json"),
    "c3b_u8": ("granular_valid_general_fs_c3b_u8.json",
               "granular_valid_c3b_u8_timed_2026-12-07b.json"),
    "c32m3b": ("granular_valid_general_fs_c32m3b.json",
               "granular_valid_c32m3b_timed_2026-12-07b.json"),
    "c32m3b_u8": ("granular_valid_general_fs_c32m3b_u8.json",
                  "granular_valid_c32m3b_u8_timed_2026-12-07b.json"),
}


def read(name: str | Path) -> dict:
    path = protocol.results_path(name)
    if not path.exists():
        raise SystemExit(f"granular_front: no record {path}")
    return json.loads(path.read_text())


def point(label: str, accuracy_file: str, timed_file: str) -> dict:
    """One model's point: the accuracy record's own mean error over its cases (its ``all``
    row of :func:`diffgns.graph.evaluate.per_family`), median speed-up of the
    timed record (2 threads and, when recorded, 1 thread pinned), with both records'
    provenance. Refuses an invalid timed record or a pair on different data. The two records
    may name one model two ways (``gns_general`` is ``soup4u8``'s weights, shipped); the
    pairs are the caller's claim, and both names are kept in the JSON."""
    acc, timed = read(accuracy_file), read(timed_file)
    if not timed.get("valid", False):
        raise SystemExit(f"granular_front: {timed_file} is not protocol-valid (load "
                         f"{timed.get('protocol', {}).get('load_before_1_5_15')}): not a figure")
    rows = [r for r in timed["rows"] if "speedup_vs_mpm_stable" in r]
    if not rows:
        raise SystemExit(f"granular_front: {timed_file} has no timed case (--timed)")
    if Path(str(acc.get("data"))).name != Path(str(timed.get("data"))).name:
        raise SystemExit(f"granular_front: {label}: {accuracy_file} and {timed_file} are on "
                         f"different data ({acc.get('data')} against {timed.get('data')})")
    pinned = timed.get("one_thread_pinned")
    pinned_rows = pinned.get("rows", []) if isinstance(pinned, dict) else []
    every = acc["table"]["all"]  # per_family's aggregate over the record's cases
    out = dict(
        label=label, model_accuracy=acc.get("model"), model_timed=timed.get("model"),
        cases=every["cases"], timed_cases=len(rows),
        mean_error=every[f"{ERROR}_mean"], max_error=every[f"{ERROR}_max"],
        mean_runout_error=every["flow_runout_rel_error_mean"],
        speedup_median=statistics.median(r["speedup_vs_mpm_stable"] for r in rows),
        speedup_min=min(r["speedup_vs_mpm_stable"] for r in rows),
        speedup_max=max(r["speedup_vs_mpm_stable"] for r in rows),
        speedup_median_pinned=(statistics.median(r["speedup_vs_mpm_stable"]
                                                 for r in pinned_rows) if pinned_rows else None),
        accuracy_file=accuracy_file, timed_file=timed_file)
    p = timed.get("protocol", {})
    out.update(timed_date_utc=p.get("date_utc"), timed_load_1min=p.get("load_before_1_5_15",
                                                                         [None])[0],
               timed_steal=p.get("cpu_steal_during_run"), timed_commit=p.get("git_commit"),
               timed_command=p.get("command"))
    return out


def plot(points: list[dict], path: Path) -> None:
    plt = protocol.use_agg()
    fig, ax = plt.subplots(figsize=(7.5, 5))
    ax.fill_between([TARGET_SPEEDUP, 40], 0.01, TARGET_ERROR, color="tab:green", alpha=0.15,
                    label=f"issue 21's targets (≥ {TARGET_SPEEDUP:g}×, ≤ {TARGET_ERROR:g})")
    for i, p in enumerate(points):  # sorted by speed-up: labels go round the point
        ax.errorbar(p["speedup_median"], p["mean_error"],
                    xerr=[[p["speedup_median"] - p["speedup_min"]],
                          [p["speedup_max"] - p["speedup_median"]]],
                    fmt="o", color="tab:red", ecolor="0.6", ms=5, capsize=2, zorder=3)
        if p["speedup_median_pinned"]:
            ax.plot(p["speedup_median_pinned"], p["mean_error"], "x", color="tab:blue", zorder=3)
        ax.annotate(p["label"], (p["speedup_median"], p["mean_error"]), fontsize=6,
                    xytext=LABEL_OFFSETS[i % len(LABEL_OFFSETS)], textcoords="offset points",
                    ha="left" if LABEL_OFFSETS[i % len(LABEL_OFFSETS)][0] > 0 else "right")
    ax.plot([], [], "o", color="tab:red", label="2 threads: median (bar: min–max of 8 cases)")
    ax.plot([], [], "x", color="tab:blue", label="1 thread pinned: median")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(1, 40)
    ax.set_ylim(0.03, 1)
    ax.set_xlabel("cheaper than the stable-dt MPM per simulated second (same-run ratio)")
    ax.set_ylabel("mean final position error / displacement (validation)")
    ax.set_title("General granular GNS: accuracy against cost (timed records of "
                 f"{min(p['timed_date_utc'][:10] for p in points)} to "
                 f"{max(p['timed_date_utc'][:10] for p in points)})", fontsize=9)
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pair", nargs=3, action="append", metavar=("LABEL", "ACCURACY", "TIMED"),
                    help="a model's accuracy and timed records (default: the committed set)")
    ap.add_argument("--out", default="granular_front", help="results/<out>.json and .png")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "granular_front", timed=False)  # no measurement: never refused
    pairs = args.pair or [(k, *v) for k, v in DEFAULT_PAIRS.items()]
    points = sorted((point(*p) for p in pairs), key=lambda p: p["speedup_median"])
    run.print(f"{'model':<28} {'error':>6} {'runout':>6} {'speed-up 2 thr (min-max)':>26} "
              f"{'pinned':>7}  timed")
    for p in points:
        pin = f"{p['speedup_median_pinned']:.1f}x" if p["speedup_median_pinned"] else "-"
        run.print(f"{p['label']:<28} {p['mean_error']:>6.3f} {p['mean_runout_error']:>6.3f} "
                  f"{p['speedup_median']:>8.1f}x ({p['speedup_min']:.1f}-"
                  f"{p['speedup_max']:.1f}x){'':>7} {pin:>7}  {p['timed_date_utc']}, load "
                  f"{p['timed_load_1min']:.2f}")
    path = run.finish(f"{args.out}.json",
                      dict(targets=dict(error=TARGET_ERROR, speedup=TARGET_SPEEDUP),
                           points=points),
                      figures=lambda json_path: plot(points, json_path.with_suffix(".png")))
    run.print(f"wrote {path} and {path.with_suffix('.png')}")


if __name__ == "__main__":
    main()
