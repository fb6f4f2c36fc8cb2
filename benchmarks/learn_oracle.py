"""How much any fixed λ on a grid gains over the paper's λ on bench_learn's labelled sets: a
reference for learning λ (issue 16).

For a grid of (λ_main, λ_position) (λ_lateral = 1, no thickness term), every pair of each
labelled set is registered at that λ (`pairwise_distances`) and scored on the same folds as
`bench_learn.py` (5 stratified folds repeated on 3 splits, seeds 0–2): 1-NN, nearest class
mean and held-out log-loss (`rootshape_jax.fold_accuracy`). Choosing λ by these scores uses
the held-out roots, so none of this is a result; it says how much room λ leaves on a set:

- *best fixed λ in hindsight*: the grid λ with the best mean score over the folds (ties go to
  the paper's λ), with its p against the paper's λ (`rootshape_jax.fold_t_test`, the
  corrected resampled t-test bench_learn uses; optimistic, as that λ is the best of many on
  the same folds);
- *smallest p on the grid*: the smallest p of any grid λ that scores better than the paper's
  λ in the mean (a λ with a smaller but steadier gain can have a smaller p than the best
  mean). When even it is at least 0.05, no *fixed* λ on the grid can be shown to beat the
  paper's λ with these folds. A learned λ changes from fold to fold and between grid points,
  so this is a reference for it, not a proof about it;
- *per-fold oracle*: each fold's best score over the grid, a bound of the mean score that a λ
  chosen per fold on this grid can reach (no p: the paper's λ is on the grid, so it is never
  behind it in any fold).

The learned λ's fold scores are read from `results/learn_weights.json` (`--learned`) when its
folds are these (checked: the paper's λ must score the same there and here).

    python benchmarks/learn_oracle.py [--sets plate,species,conditions] [--T 32] [--markdown-only]

Writes results/learn_oracle.json and results/learn_oracle.md (appended by
paper_reproduction.py to its report, after learn_weights.md).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _common import RESULTS, machine, setup_jax  # noqa: E402

MAINS = (0.001, 0.002, 0.005, 0.02, 0.05, 0.2, 0.5)
POSITIONS = (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)
PAPER = (0.02, 1.0)
SCORES = (("nn", "1-NN", True), ("mean", "nearest class mean", True), ("log_loss", "held-out log-loss", False))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sets", default="plate,species,conditions")
    p.add_argument("--T", type=int, default=32)
    p.add_argument("--n-folds", type=int, default=5)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--learned", default=str(RESULTS / "learn_weights.json"), help="bench_learn's JSON")
    p.add_argument("--out", default=str(RESULTS))
    p.add_argument("--markdown-only", action="store_true", help="rewrite the markdown from the JSON")
    args = p.parse_args(argv)
    out = Path(args.out)
    learned = json.loads(Path(args.learned).read_text()) if Path(args.learned).exists() else None
    if args.markdown_only:
        results = json.loads((out / "learn_oracle.json").read_text())
        for tag, row in results["sets"].items():  # bench_learn's JSON may be newer than this one
            for stale in ("learned_scores", "paper_matches_bench_learn", "paper_largest_difference"):
                row.pop(stale, None)
            row.update(learned_scores(learned, tag, row, results["args"]))
        (out / "learn_oracle.md").write_text(markdown(results))
        return results

    setup_jax()  # as bench_learn, whose fold scores these are compared with
    from bench_learn import labelled_sets

    import rootshape_jax as rs

    results = {"machine": machine(), "args": vars(args), "grid": {"main": MAINS, "position": POSITIONS}, "sets": {}}
    for tag, (roots, labels, what) in labelled_sets(args.sets.split(","), False).items():
        y = np.asarray(labels)
        trees = rs.batch(roots, n_points=args.T, normalise_scale=True)
        row = {"what": what, "n": len(y), "grid_scores": {}}
        t_set = time.perf_counter()
        for lm, lp in itertools.product(MAINS, POSITIONS):
            t0 = time.perf_counter()
            D = np.asarray(
                rs.pairwise_distances(trees, weights=rs.Weights(main=lm, lateral=1.0, position=lp), progress=False),
                np.float64,
            )
            acc = rs.fold_accuracy(0.5 * (D + D.T), y, n_folds=args.n_folds, seed=args.seed, n_repeats=args.repeats)
            row["grid_scores"][_key((lm, lp))] = {k: np.asarray(acc[k], np.float64).tolist() for k, _, _ in SCORES}
            print(
                f"{tag}: λ_main {lm:g}, λ_position {lp:g}: 1-NN {100 * np.mean(acc['nn']):.1f} %, "
                f"log-loss {np.mean(acc['log_loss']):.3f} ({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )
        row["seconds"] = time.perf_counter() - t_set
        row.update(learned_scores(learned, tag, row, vars(args)))
        results["sets"][tag] = row
        out.mkdir(parents=True, exist_ok=True)
        (out / "learn_oracle.json").write_text(json.dumps(results, indent=1))
    text = markdown(results)
    (out / "learn_oracle.md").write_text(text)
    print(text)
    return results


def _key(lam) -> str:
    return f"{lam[0]:g},{lam[1]:g}"


def learned_scores(learned: dict | None, tag: str, row: dict, args: dict) -> dict:
    """The learned λ's fold scores from bench_learn's JSON, when its folds are these: same T,
    folds, seed and splits, and the paper's λ scoring the same fold by fold."""
    if learned is None or tag not in learned.get("sets", {}):
        return {}
    la = learned.get("args", {})
    mine = (args["T"], args["n_folds"], args["seed"], args["repeats"])
    if (la.get("T"), la.get("n_folds"), la.get("seed"), la.get("repeats", 1)) != mine:
        return {"paper_matches_bench_learn": False, "paper_largest_difference": None}
    acc = learned["sets"][tag].get("accuracy", {})
    if "paper" not in acc or "learned" not in acc:
        return {"paper_matches_bench_learn": False, "paper_largest_difference": None}
    paper = row["grid_scores"][_key(PAPER)]
    gap = max(float(np.max(np.abs(np.asarray(acc["paper"][k]) - np.asarray(paper[k])))) for k, _, _ in SCORES)
    out = {"paper_matches_bench_learn": gap < 1e-3, "paper_largest_difference": gap}
    if gap < 1e-3:
        out["learned_scores"] = {k: acc["learned"][k] for k, _, _ in SCORES}
    return out


def summary(row: dict, grid: dict, n_folds: int) -> dict:
    """Per score: the paper's λ, the learned λ, the best fixed λ in hindsight, the smallest p on
    the grid (unadjusted, and Holm-adjusted over the λ it is the smallest of) and the per-fold
    oracle (see the module docstring)."""
    import rootshape_jax as rs

    keys = list(row["grid_scores"])
    paper_key = _key(PAPER)
    out = {}
    for k, _, higher in SCORES:
        scores = {key: np.asarray(row["grid_scores"][key][k]) for key in keys}
        paper = scores[paper_key]
        sign = 1.0 if higher else -1.0
        means = {key: sign * float(np.mean(v)) for key, v in scores.items()}
        top = max(means.values())
        tied = [key for key in keys if means[key] >= top - 1e-12]
        # Ties (within rounding) go to the paper's λ, then to an inner grid λ, then to the first.
        inner = [key for key in tied if not _on_edge(key, grid)]
        best = paper_key if paper_key in tied else (inner or tied)[0]
        better = [key for key in keys if means[key] > means[paper_key] + 1e-12]
        tests = {key: rs.fold_t_test(scores[key], paper, n_folds=n_folds).p_value for key in better}
        # NaN: the λ gains the same amount in every fold (no spread to test against).
        finite = {key: p for key, p in tests.items() if not math.isnan(p)}
        stacked = np.stack(list(scores.values()))
        entry = {
            "paper": float(np.mean(paper)),
            "hindsight_lambda": best,
            "hindsight": float(np.mean(scores[best])),
            "hindsight_p": None if best == paper_key else rs.fold_t_test(scores[best], paper, n_folds=n_folds).p_value,
            "hindsight_on_edge": all(_on_edge(key, grid) for key in tied) and not (higher and top >= 1.0),
            "n_better": len(better),
            "n_undefined_p": len(tests) - len(finite),
            "smallest_p": min(finite.values()) if finite else None,
            "smallest_p_lambda": min(finite, key=finite.get) if finite else None,
            "smallest_p_holm": float(np.min(rs.holm(list(finite.values())))) if finite else None,
            "oracle": float(np.mean(stacked.max(axis=0) if higher else stacked.min(axis=0))),
        }
        if "learned_scores" in row:
            ls = np.asarray(row["learned_scores"][k])
            entry["learned"] = float(np.mean(ls))
            entry["learned_p"] = rs.fold_t_test(ls, paper, n_folds=n_folds).p_value
        out[k] = entry
    return out


def _on_edge(key: str, grid: dict) -> bool:
    lm, lp = (float(x) for x in key.split(","))
    return lm in (min(grid["main"]), max(grid["main"])) or lp in (min(grid["position"]), max(grid["position"]))


def _p(p) -> str:
    return "undefined" if p is None or p != p else f"{p:.3g}"


def markdown(results: dict) -> str:
    a = results["args"]
    grid = results["grid"]
    lines = [
        "### How much room λ leaves on each set (a reference, not a result)",
        "",
        f"Generated by `python benchmarks/learn_oracle.py --sets {a['sets']} --T {a['T']}` "
        f"({results['machine'].get('date', '')}, package at {results['machine'].get('git', '?')}). Every pair "
        f"of each set registered at each λ of a grid, λ_main in {list(grid['main'])} × λ_position in "
        f"{list(grid['position'])} (λ_lateral = 1), and scored on the same {a['n_folds']} folds × "
        f"{a['repeats']} splits as bench_learn's table (`learn_weights.md`). These pick λ by the held-out "
        "roots, so they are no result: they say how much a better λ could gain on a set at all. *Best "
        "fixed λ in hindsight*: the grid λ (λ_main, λ_position) with the best mean score (ties to the "
        "paper's λ, then to a λ inside the grid), and its p against the paper's λ (`fold_t_test`, "
        "unadjusted; optimistic, being the best of many λ on the same folds); *(grid edge)*: every λ with "
        "that score is on the grid's border, so a λ beyond it may do better still. *Smallest p*: the "
        "smallest unadjusted p of the N grid λ better than the paper's in the mean (a steadier, smaller "
        "gain can test better than the best mean), and Holm-adjusted over those N. At 0.05 or above "
        "unadjusted, no fixed λ on the grid can be shown to beat the paper's λ with these folds; below "
        "0.05 after Holm, some can. A learned λ changes from fold to fold and lies between grid points, "
        "so this is a reference for it, not a bound on its p. *Per-fold oracle*: the mean of each fold's "
        "best score on the grid, the most a λ chosen per fold on this grid could reach (no p: it is "
        "never behind the paper's λ, which is on the grid).",
        "",
        "| set | score | paper λ | learned λ (nested CV), p | best fixed λ in hindsight, p | smallest p on the grid (N; Holm) | per-fold oracle |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    readings = []
    for tag, row in results["sets"].items():
        summ = summary(row, grid, a["n_folds"])
        beyond, unsure, within, none = [], [], [], []
        for k, name, _ in SCORES:
            e = summ[k]

            def fmt(v, k=k):
                return f"{100 * v:.1f} %" if k != "log_loss" else f"{v:.3f}"

            learned = f"{fmt(e['learned'])}, {_p(e['learned_p'])}" if "learned" in e else "—"
            best = (
                "("
                + e["hindsight_lambda"].replace(",", ", ")
                + ")"
                + (" (grid edge)" if e["hindsight_on_edge"] else "")
            )
            hind = f"{fmt(e['hindsight'])} at {best}" + (
                f", {_p(e['hindsight_p'])}" if e["hindsight_p"] is not None else ""
            )
            if e["n_better"] == 0:
                small = "— (none better)"
            elif e["smallest_p"] is None:
                small = f"undefined ({e['n_better']})"
            else:
                small = (
                    f"{_p(e['smallest_p'])} at ({e['smallest_p_lambda'].replace(',', ', ')}) "
                    f"({e['n_better']}; {_p(e['smallest_p_holm'])})"
                )
            lines.append(
                f"| {tag} (n = {row['n']}) | {name} | {fmt(e['paper'])} | {learned} | {hind} | {small} | "
                f"{fmt(e['oracle'])} |"
            )
            undefined = (
                f"; {e['n_undefined_p']} of them gain the same in every fold, p undefined" if e["n_undefined_p"] else ""
            )
            if e["n_better"] == 0:
                none.append(name)
            elif e["smallest_p"] is None:
                within.append(f"{name} (every better λ gains the same in every fold: p undefined)")
            elif e["smallest_p_holm"] < 0.05:
                beyond.append(f"{name} (smallest p {_p(e['smallest_p'])}, Holm {_p(e['smallest_p_holm'])}{undefined})")
            elif e["smallest_p"] < 0.05:
                unsure.append(
                    f"{name} (smallest p {_p(e['smallest_p'])} of {e['n_better']}, Holm {_p(e['smallest_p_holm'])}"
                    f"{undefined})"
                )
            else:
                within.append(f"{name} (smallest p {_p(e['smallest_p'])}{undefined})")
        parts = []
        if beyond:
            parts.append(
                "some fixed λ on the grid beats the paper's λ beyond the folds' spread on " + ", ".join(beyond)
            )
        if unsure:
            parts.append(
                "some fixed λ beats the paper's λ at p < 0.05 unadjusted but not after Holm over the grid on "
                + ", ".join(unsure)
            )
        if within:
            parts.append("no fixed λ on the grid beats the paper's λ beyond the folds' spread on " + ", ".join(within))
        if none:
            parts.append("no λ on the grid scores better than the paper's λ on " + ", ".join(none))
        e = summ["log_loss"]
        if "learned" in e and e["hindsight"] < e["paper"]:
            share = (e["paper"] - e["learned"]) / (e["paper"] - e["hindsight"])
            parts.append(
                f"the learned λ (from the training roots only) has {100 * share:.0f} % of the best fixed "
                "λ's log-loss gain"
            )
        readings.append(f"- {tag}: " + "; ".join(parts) + ".")
        if row.get("paper_matches_bench_learn") is False:
            gap = row.get("paper_largest_difference")
            why = "its folds differ" if gap is None else f"the paper's λ scores up to {gap:.3g} differently there"
            readings.append(f"  (The learned column is left out: {why}.)")
    return "\n".join(lines + [""] + readings) + "\n"


if __name__ == "__main__":
    main()
