"""Figures of a ``jepa-monitor compare --out FILE.json`` result: the natural-failure ROC curves (per checkpoint and
view) and the median alert delay after a fault's onset (per single-signal detector and fault). matplotlib is
imported only when a figure is drawn: the monitor's image installs none (``pip install .[monitor,plot]`` for
figures beside it).

    python3 -m monitor_service.offline.figures compare.json --out DIR
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

OURS, RANDOM = "nmse", "random"


def pyplot():
    """matplotlib's pyplot on the Agg backend; ImportError naming the extra when it is not installed."""
    try:
        import matplotlib
    except ImportError:
        raise ImportError("the offline study's figures need matplotlib: pip install matplotlib (the project's "
                          "plot extra)") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def roc_figure(result: dict, path: Path) -> Path:
    """One panel per (checkpoint, view): every signal's ROC of natural failures against natural successes."""
    plt = pyplot()
    groups = list(result["groups"])
    views = list(next(iter(result["groups"].values()))["views"])
    fig, axes = plt.subplots(len(groups), len(views), figsize=(4.6 * len(views), 4.2 * len(groups)), squeeze=False)
    for gi, group in enumerate(groups):
        g = result["groups"][group]
        for vi, view in enumerate(views):
            ax, v = axes[gi][vi], g["views"][view]
            for signal in g["signals"]:
                r = v["ranking"]["natural"].get(signal, {})
                if "roc" not in r:
                    continue
                ax.plot(r["roc"]["fpr"], r["roc"]["tpr"], drawstyle="steps-post", lw=2.4 if signal == OURS else 1.2,
                        ls="--" if signal == RANDOM else "-", label=f"{signal} {r['auroc']:.2f}")
            ax.plot([0, 1], [0, 1], ":", color="grey", lw=1)
            cut = f", first {v['decisions']} decisions" if v.get("decisions") else ""
            ax.set(title=f"{g.get('arm') or group}: natural failures ({view}{cut})", xlabel="false-alarm rate",
                   ylabel="failures ranked above")
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def delay_figure(result: dict, path: Path) -> Path | None:
    """Median alert delay after onset (decisions) of each single-signal detector (successes calibration, the
    first rule) on each fault, whole episodes; None when the result has no fault."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(10, 4.4))
    marks = "osD^v<>pPX*h"
    regimes, rule = [], None
    for gi, (group, g) in enumerate(result["groups"].items()):
        v = g["views"].get("whole") or next(iter(g["views"].values()))
        rule = next(iter(v["detection"]))
        regimes = [r for r in v["ranking"] if r != "natural"]
        detectors = v["detection"][rule]["detectors"]
        for si, signal in enumerate(g["signals"]):
            name = next((n for n in detectors if n.split(" ")[0] == signal and "[labelled]" not in n), None)
            if name is None:
                continue
            xs, ys = [], []
            for ri, regime in enumerate(regimes):
                q = detectors[name][regime].get("delay_decisions")
                if q is not None and detectors[name][regime]["failures"]:
                    xs.append(ri + 0.06 * (si - len(g["signals"]) / 2) + 0.03 * gi)
                    ys.append(q["median"])
            ax.scatter(xs, ys, marker=marks[si % len(marks)], s=30, alpha=0.9 if gi == 0 else 0.5,
                       label=f"{signal} ({g.get('arm') or group})")
    if not regimes:
        plt.close(fig)
        return None
    ax.set_xticks(range(len(regimes)), regimes, rotation=30, ha="right", fontsize=8)
    ax.axhline(2, color="grey", ls=":", lw=1)
    ax.set(ylabel="median delay after onset (decisions)", title=f"alert delay on injected faults (rule {rule})")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=6, ncol=4)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python3 -m monitor_service.offline.figures", description=__doc__.split("\n\n")[0])
    p.add_argument("result", help="the JSON file of jepa-monitor compare --out FILE.json")
    p.add_argument("--out", required=True, help="folder for compare_roc.png and compare_delay.png")
    args = p.parse_args(argv)
    try:
        result = json.loads(Path(args.result).read_text())
        if "groups" not in result:
            raise ValueError("not a jepa-monitor compare result (no 'groups'); write one with --out FILE.json")
    except (OSError, ValueError) as exc:
        print(f"figures: error: {args.result}: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    files = [roc_figure(result, out / "compare_roc.png"), delay_figure(result, out / "compare_delay.png")]
    for f in files:
        if f is not None:
            print(f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
