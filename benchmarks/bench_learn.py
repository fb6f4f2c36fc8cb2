"""Learned metric weights under nested cross-validation, against the paper's λ and baselines.

For each labelled set (bundled synthetic conditions, CPlantBox species, the Arabidopsis plate
dates of ../shared/data) the roots are resampled (T points) and scale-normalised, and scored on
the same stratified folds (seeded) by:

- learned λ: `rootshape_jax.nested_cv_accuracy` (λ learned on the training folds only);
- the paper's λ (0.02, 1, 1) — the same call, same folds;
- QED, fc-SRVF, tree edit distance, TMD (`rootshape_jax.baselines`): `fold_accuracy` of their
  distance matrices on the same folds (nothing learned).

1-NN and nearest-class-mean (centroid from distances, no Karcher mean) accuracy on held-out
roots, mean ± standard deviation over folds. It also times `learn_weights` on the bundled 53
(wall and process CPU time). Writes results/learn_weights.json and results/learn_weights.md
(appended by paper_reproduction.py to its report).

    python benchmarks/bench_learn.py [--T 32] [--sets conditions,species,plate] [--quick]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _common import RESULTS, machine, setup_jax  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
METHODS = ("learned", "learned_cv", "paper", "ted", "qed", "fc_srvf", "tmd")
LABEL = {
    "learned": "ours, learned λ (nested CV)",
    "learned_cv": "ours, learned λ, penalty chosen by inner CV (nested CV)",
    "paper": "ours, paper λ (0.02, 1, 1)",
    "ted": "tree edit distance",
    "qed": "QED (Feragen et al.)",
    "fc_srvf": "fc-SRVF (Wang et al.)",
    "tmd": "TMD (Kanari et al.)",
}


def labelled_sets(names, quick: bool):
    import rootshape_jax.datasets as ds
    from rootshape_jax.io import read_rsml

    out = {}
    if "conditions" in names:
        roots = ds.default_dataset()
        if quick:
            seen: dict = {}
            roots = [
                r
                for r in roots
                if seen.setdefault(r.metadata["condition"], []).append(r) or len(seen[r.metadata["condition"]]) <= 5
            ]
        out["conditions"] = (roots, [r.metadata["condition"] for r in roots], "bundled synthetic conditions")
    if "species" in names:
        roots = []
        for sp in ("wheat", "maize", "pea"):
            roots += ds.simulated_roots(sp, 5 if quick else 10, days=12.0, seed=0, dim=2)
        out["species"] = (roots, [r.metadata["species"] for r in roots], "CPlantBox species (12 days, 2-D)")
    if "plate" in names:
        folder = DATA / "rsml" / "arabidopsis_plate"
        if folder.is_dir():
            roots, labels = [], []
            for f in sorted(folder.glob("*.rsml")):
                date = "_".join(f.name.split("_")[:4])  # 2012_11_19_18h00
                for r in read_rsml(f):
                    roots.append(r)
                    labels.append(date)
            out["plate"] = (roots, labels, "Arabidopsis plate, label = date (3 dates × 5 seedlings)")
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--T", type=int, default=32)
    p.add_argument(
        "--sets", default="plate,conditions,learn53,species", help="in this order; learn53 times learn_weights"
    )
    p.add_argument("--n-folds", type=int, default=5)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--repeats", type=int, default=1, help="repeat the CV on this many splits (seeds seed, seed + 1, ...)"
    )
    p.add_argument("--max-reregistrations", type=int, default=3, help="per fold of the nested CV")
    p.add_argument("--learn-reregistrations", type=int, default=4, help="for the 53-root timing")
    p.add_argument(
        "--grid",
        default="",
        help="also score λ learned with the penalty chosen by inner CV among these values (e.g. 1e-3,1e-2,0.1,1)",
    )
    p.add_argument(
        "--merge",
        default="",
        help="comma-separated result folders (FOLDER[:set+set[:earlier]]) whose sets are merged into --out",
    )
    p.add_argument("--generated-by", default="", help="with --merge: the commands that made the parts (report text)")
    p.add_argument("--quick", action="store_true", help="5 roots per class, no 53-root timing")
    p.add_argument("--out", default=str(RESULTS))
    p.add_argument("--markdown-only", action="store_true", help="rewrite the markdown from the JSON")
    args = p.parse_args(argv)
    if args.merge:
        merged: dict = {}
        merged_split: dict = {}
        for item in args.merge.split(","):
            # FOLDER, FOLDER:set+set, or FOLDER:set+set:earlier (rows of an earlier version's run)
            folder, _, rest = item.partition(":")
            only, _, earlier = rest.partition(":")
            part = json.loads((Path(folder) / "learn_weights.json").read_text())
            if only:
                part["sets"] = {k: v for k, v in part["sets"].items() if k in only.split("+")}
            split = {k: part["args"].get(k, 1 if k == "repeats" else None) for k in ("n_folds", "seed", "repeats")}
            if merged and part["sets"] and split != merged_split:
                # Fold-by-fold comparisons and the report's one description need the same folds.
                raise SystemExit(f"--merge: {folder} was split with {split}, the first part with {merged_split}")
            if not merged:
                merged, merged_split = part, split
            else:
                if part.get("learn_53"):  # a later folder's timing replaces an earlier one
                    merged["learn_53"] = {  # a merged record keeps the load it was measured at
                        "load_before": part["machine"].get("load_average_1min_at_start"),
                        **part["learn_53"],
                    }
                for tag, row in part["sets"].items():
                    row["max_reregistrations_run"] = part["args"]["max_reregistrations"]
                    if earlier:
                        keys = ("T", "n_folds", "seed", "repeats", "max_reregistrations")
                        row["note"] = "from an earlier run of this script (its older stopping rule), with " + ", ".join(
                            f"{k} {part['args'].get(k)}" for k in keys
                        )
                    if tag in merged["sets"]:  # a later folder adds its extra rows to a set
                        merged["sets"][tag]["accuracy"].update(row["accuracy"])
                        seconds = merged["sets"][tag]["seconds"]
                        seconds.update({k: v for k, v in row["seconds"].items() if k not in seconds})
                        merged["sets"][tag].update({k: v for k, v in row.items() if k.endswith("_cv")})
                    else:
                        merged["sets"][tag] = row
        if merged.get("learn_53") is None:
            merged.pop("learn_53", None)
        merged["generated_by"] = args.generated_by
        (Path(args.out) / "learn_weights.json").write_text(json.dumps(merged, indent=1))
        (Path(args.out) / "learn_weights.md").write_text(markdown(merged))
        return
    if args.markdown_only:
        results = json.loads((Path(args.out) / "learn_weights.json").read_text())
        (Path(args.out) / "learn_weights.md").write_text(markdown(results))
        return
    setup_jax()
    import numpy as np

    import rootshape_jax as rs
    from rootshape_jax import baselines as bl

    info = machine()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {"machine": info, "args": vars(args), "sets": {}}
    sets = labelled_sets([t for t in args.sets.split(",") if t != "learn53"], args.quick)
    for tag in args.sets.split(","):
        if tag == "learn53":
            if "conditions" not in sets:
                sets.update(labelled_sets(["conditions"], False))
            roots, labels, _ = sets["conditions"]
            print(f"== learn_weights on {len(roots)} roots", flush=True)
            results["learn_53"] = time_learning(rs, roots, labels, args.T, args.learn_reregistrations)
            print(results["learn_53"], flush=True)
            (out / "learn_weights.json").write_text(json.dumps(results, indent=1))
            continue
        if tag not in sets:
            print(f"== {tag}: not available, skipped", flush=True)
            continue
        roots, labels, what = sets[tag]
        print(f"== {tag}: {len(roots)} roots", flush=True)
        trees = rs.batch(roots, n_points=args.T, normalise_scale=True)
        base = rs.to_roots(trees)
        y = np.asarray(labels)
        row = {"what": what, "n": len(roots), "classes": {c: int(np.sum(y == c)) for c in np.unique(y)}}
        row["K"] = int(trees.capacity)
        mats, secs = {}, {}
        for m, fn in (
            ("ted", lambda: bl.tree_edit_distance_matrix(base)),
            ("qed", lambda: bl.qed_distance_matrix(base, n_landmarks=20)),
            ("fc_srvf", lambda: bl.fc_srvf_distance_matrix(base, n_points=args.T, progress=False)),
            ("tmd", lambda: bl.tmd_distance_matrix(base)),
        ):
            t0 = time.perf_counter()
            D = np.asarray(fn(), np.float64)
            mats[m] = 0.5 * (D + D.T)
            secs[m] = time.perf_counter() - t0
        acc = {
            m: rs.fold_accuracy(mats[m], y, n_folds=args.n_folds, seed=args.seed, n_repeats=args.repeats) for m in mats
        }
        t0, c0 = time.perf_counter(), time.process_time()
        cv = rs.nested_cv_accuracy(
            trees,
            y,
            n_folds=args.n_folds,
            seed=args.seed,
            n_repeats=args.repeats,
            max_reregistrations=args.max_reregistrations,
        )
        secs["nested_cv"] = time.perf_counter() - t0
        secs["nested_cv_cpu"] = time.process_time() - c0
        acc["learned"] = {"nn": cv.learned_nn, "mean": cv.learned_mean, "log_loss": cv.learned_log_loss}
        acc["paper"] = {"nn": cv.paper_nn, "mean": cv.paper_mean, "log_loss": cv.paper_log_loss}
        row["accuracy"] = {m: {k: [float(x) for x in v] for k, v in a.items()} for m, a in acc.items()}  # per fold
        row["fold_weights"] = cv.weights
        row["fold_status"] = list(cv.status)
        row["fold_reregistrations"] = cv.n_reregistrations.tolist()
        row["fold_learning_s"] = cv.seconds_learning.tolist()
        if args.grid:
            grid = [float(x) for x in args.grid.split(",")]
            t0 = time.perf_counter()
            cvg = rs.nested_cv_accuracy(
                trees,
                y,
                n_folds=args.n_folds,
                seed=args.seed,
                n_repeats=args.repeats,
                max_reregistrations=args.max_reregistrations,
                regularisation=grid,
            )
            secs["nested_cv_grid"] = time.perf_counter() - t0
            row["accuracy"]["learned_cv"] = {
                "nn": cvg.learned_nn.tolist(),
                "mean": cvg.learned_mean.tolist(),
                "log_loss": cvg.learned_log_loss.tolist(),
            }
            row["fold_weights_cv"] = cvg.weights
            row["fold_status_cv"] = list(cvg.status)
            row["fold_reregistrations_cv"] = cvg.n_reregistrations.tolist()
            row["fold_regularisation_cv"] = cvg.regularisation.tolist()
            row["grid_cv"] = grid
        row["seconds"] = secs
        row["chance"] = float(max(np.sum(y == c) for c in np.unique(y)) / len(y))
        results["sets"][tag] = row
        print(json.dumps({m: {k: float(np.mean(v)) for k, v in a.items()} for m, a in acc.items()}), flush=True)
        (out / "learn_weights.json").write_text(json.dumps(results, indent=1))
    (out / "learn_weights.json").write_text(json.dumps(results, indent=1))
    (out / "learn_weights.md").write_text(markdown(results))
    print((out / "learn_weights.md").read_text())


def time_learning(rs, roots, labels, T, max_reregistrations):
    """`learn_weights` on all the roots: wall and process CPU time (compilation included)."""
    import os

    trees = rs.batch(roots, n_points=T, normalise_scale=True)
    t0, c0 = time.perf_counter(), time.process_time()
    res = rs.learn_weights(trees, labels, max_reregistrations=max_reregistrations)
    return {
        "wall_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,
        "weights": {k: float(v) for k, v in res.weights.items()},
        "loss_trace": res.loss_trace.tolist(),
        "inner_loss_trace": res.inner_loss_trace.tolist(),
        "status": res.status,
        "steps": res.steps,
        "n_reregistrations": res.n_reregistrations,
        "changed_pairs": res.changed_pairs.tolist(),
        "registration_gain": res.registration_gain.tolist(),
        "max_reregistrations": max_reregistrations,
        "load_after": os.getloadavg()[0],
    }


def pct(v) -> str:
    import numpy as np

    return f"{100 * np.mean(v):.1f} ± {100 * np.std(v):.1f} %"


def markdown(results) -> str:
    import numpy as np

    from rootshape_jax import holm
    from rootshape_jax._learn import fold_better, fold_t_test

    a = results["args"]
    default_command = f"`python benchmarks/bench_learn.py --T {a['T']}`"
    lines = [
        "## (i) Learned metric weights (nested cross-validation)",
        "",
        f"Generated by {results.get('generated_by') or default_command} "
        "(results/learn_weights.json). "
        f"Roots resampled to T = {a['T']} points per branch and scale-normalised; "
        + (
            f"{a['n_folds']} stratified folds (seed {a['seed']}), the same folds for every method. "
            if a.get("repeats", 1) == 1
            else f"{a['n_folds']} stratified folds, repeated on {a['repeats']} splits (seeds {a['seed']}–"
            f"{a['seed'] + a['repeats'] - 1}; `n_repeats={a['repeats']}`), {a['n_folds'] * a['repeats']} folds "
            "in all, the same folds for every method. "
        )
        + "Accuracy is on the held-out fold only, mean ± standard deviation over folds; nothing "
        "here is training accuracy. *Learned λ*: `rootshape_jax.nested_cv_accuracy` learns λ on "
        "the training folds only (NCA loss, λ_lateral = 1 fixed, softness 0.1, up to "
        f"{a['max_reregistrations']} re-registrations), then registers the held-out roots onto "
        "the training roots at that λ. *Paper λ*: (0.02, 1, 1), same call. Baselines: their "
        "distance matrices (`rootshape_jax.baselines`) on the same folds. 1-NN: label of the "
        "nearest training root; class mean: nearest class centroid computed from distances "
        "(``mean_j d²(x, x_j) − mean_jk d²(x_j, x_k)/2``, no Karcher mean). Held-out log-loss: "
        "`rootshape_jax.held_out_log_loss`, the NCA loss that the learning minimises, on the "
        "held-out roots against the training roots (lower is better; ln 3 = 1.099 is guessing "
        "among three equal classes), at the same relative temperature for every distance "
        "(τ = 0.1 · mean training d²). It grades how confidently the held-out classes are "
        "predicted, so it still separates methods where accuracy sits at or near 100 %. The "
        "learned λ is fitted at that temperature and the baselines are not, so the baselines' "
        "log-loss is a reference, not a target.",
        "",
        *(
            [
                "*Learned λ, penalty by inner CV*: the same, but the penalty toward the paper's λ, "
                "``r Σ (log λ − log λ_paper)²``, is chosen per outer fold among "
                f"{next(row['grid_cv'] for row in results['sets'].values() if 'grid_cv' in row)} by a 3-fold "
                "inner CV of that fold's training roots (held-out NCA log-loss, registrations at the "
                "paper's λ; ties to the stronger penalty); the plain row uses r = 0.001.",
                "",
            ]
            if any("grid_cv" in row for row in results["sets"].values())
            else []
        ),
        f"Machine: {results['machine'].get('cpu')}, {results['machine'].get('cores')} cores, shared "
        f"(1-min load at start {results['machine'].get('load_average_1min_at_start')}).",
        "",
        "| labelled set | distance | 1-NN | nearest class mean | held-out log-loss |",
        "|---|---|---|---|---|",
    ]
    for _tag, row in results["sets"].items():
        what = f"{row['what']} (n = {row['n']}, K = {row['K']}; chance {100 * row['chance']:.1f} %)"
        if "note" in row:
            what += f" [{row['note']}]"
        for m in METHODS:
            if m in row["accuracy"]:
                acc = row["accuracy"][m]
                loss = acc.get("log_loss")
                cell = f"{np.mean(loss):.3f} ± {np.std(loss):.3f}" if loss is not None else "—"
                lines.append(f"| {what} | {LABEL[m]} | {pct(acc['nn'])} | {pct(acc['mean'])} | {cell} |")

    def test(scores, reference):
        return fold_t_test(scores, reference, n_folds=a["n_folds"])

    def p_text(t) -> str:
        return "no spread, p undefined" if t.p_value != t.p_value else f"p = {t.p_value:.3g}"

    def word(diff: float, t) -> str:
        """diff > 0: ours better. Beats / trails only beyond the folds' spread."""
        if diff == 0:
            return "ties"
        if t.p_value < 0.05:
            return "beats" if diff > 0 else "trails"
        return "is level with"

    lines += [
        "",
        "**Against the targets** (computed from the table; differences in percentage points; p: "
        "`rootshape_jax.fold_t_test`, the corrected resampled paired t-test of Nadeau & Bengio over the "
        "same folds, two-sided, per comparison (not adjusted for the many in this list). Folds share "
        "training roots, so a plain t-test over folds would be far too confident. *Beats* / *trails*: "
        "p < 0.05; *is level with*: a difference within the folds' spread. The best baseline is "
        "picked by its mean, which makes a *beats it* conservative and a *trails it* optimistic):",
        "",
    ]
    loss_tests = {}
    for tag, row in results["sets"].items():
        acc = row["accuracy"]
        mean = {m: (100 * float(np.mean(acc[m]["nn"])), 100 * float(np.mean(acc[m]["mean"]))) for m in acc}
        base = [m for m in ("ted", "qed", "fc_srvf", "tmd") if m in mean]
        for ours in ("learned", "learned_cv"):
            if ours not in mean:
                continue
            verdict = []
            for rule, k, key in (("1-NN", 0, "nn"), ("class mean", 1, "mean")):
                d_paper = mean[ours][k] - mean["paper"][k]
                b = max(base, key=lambda m, k=k: mean[m][k])
                d_base = mean[ours][k] - mean[b][k]
                better, _, worse = fold_better(acc[ours][key], acc["paper"][key], higher_is_better=True)
                d_paper, d_base = round(d_paper, 6), round(d_base, 6)  # a float mean's last bits are no win
                t_paper, t_base = test(acc[ours][key], acc["paper"][key]), test(acc[ours][key], acc[b][key])
                verdict.append(
                    f"{rule}: {word(d_paper, t_paper)} the paper's λ "
                    f"({d_paper:+.1f}; better in {better} of {len(acc[ours][key])} folds, worse in "
                    f"{worse}; {p_text(t_paper)}) and {word(d_base, t_base)} the "
                    f"best baseline, {LABEL[b]} ({d_base:+.1f}; {p_text(t_base)})"
                )
            if "log_loss" in acc[ours] and "log_loss" in acc["paper"]:
                mine, theirs = float(np.mean(acc[ours]["log_loss"])), float(np.mean(acc["paper"]["log_loss"]))
                t_loss = test(acc[ours]["log_loss"], acc["paper"]["log_loss"])
                if ours == "learned":
                    loss_tests[tag] = t_loss
                # Fold by fold (the same folds): is the mean's difference consistent or one fold's?
                lower, _, higher = fold_better(acc[ours]["log_loss"], acc["paper"]["log_loss"], higher_is_better=False)
                verdict.append(
                    f"held-out log-loss: {word(theirs - mine, t_loss)} the paper's λ ({mine:.3f} against "
                    f"{theirs:.3f}; lower in {lower} of {len(acc[ours]['log_loss'])} folds, higher in {higher}; "
                    f"{p_text(t_loss)})"
                )
            who = "learned λ" if ours == "learned" else "learned λ, penalty by inner CV"
            lines.append(f"- {tag}, {who}: " + "; ".join(verdict) + ".")
    usable = {tag: t.p_value for tag, t in loss_tests.items() if t.p_value == t.p_value}
    if len(usable) > 1:
        adjusted = holm(list(usable.values()))
        lines += [
            "",
            "The learned λ's held-out log-loss against the paper's λ, read as one family over the "
            f"{len(usable)} sets (Holm-adjusted p): "
            + ", ".join(f"{tag} {p:.3g}" for tag, p in zip(usable, adjusted))
            + ".",
        ]
    lines += [
        "",
        "One held-out root is worth "
        + ", ".join(f"{100 * a['n_folds'] / row['n']:.0f} points ({tag})" for tag, row in results["sets"].items())
        + " of a fold's accuracy, and the fold spread is of that size: differences smaller than "
        "that are within the noise. Status of a fit: `converged` (no pair's real-lateral "
        "correspondence changed at the last re-registration), `loss` (the loss at the fresh "
        "registrations improved by less than 0.1 %; the best entry is kept), or "
        "`max_reregistrations`.",
    ]
    lines += ["", "Learned λ per fold (λ_lateral = 1) and time:", ""]
    if any("thickness" in w and w["thickness"] > 0 for row in results["sets"].values() for w in row["fold_weights"]):
        lines += [
            "(Roots with radii — the CPlantBox species — also learn λ_thickness, from a start of 1. "
            "CPlantBox gives every branch one constant radius, so the thickness channel of the "
            "extended SRVF (the change of radius along a branch) is zero: λ_thickness has no "
            "gradient and stays at 1, with no effect on the distances.)",
            "",
        ]
    for tag, row in results["sets"].items():
        ws = "; ".join(
            f"main {w['main']:.3g}, position {w['position']:.3g}"
            + (f", thickness {w['thickness']:.3g}" if w.get("thickness") else "")
            for w in row["fold_weights"]
        )
        s = row["seconds"]
        if "fold_regularisation_cv" in row:
            lines.append(
                f"- {tag}, penalty by inner CV among {row['grid_cv']}: chosen per fold "
                f"{row['fold_regularisation_cv']}; λ "
                + "; ".join(f"main {w['main']:.3g}, position {w['position']:.3g}" for w in row["fold_weights_cv"])
                + f"; re-registrations {row['fold_reregistrations_cv']}, status {', '.join(row['fold_status_cv'])}; "
                f"{s.get('nested_cv_grid', float('nan')):.0f} s wall."
            )
        lines.append(
            f"- {tag}: {ws}. Re-registrations per fold {row['fold_reregistrations']} (at most "
            f"{row.get('max_reregistrations_run', a['max_reregistrations'])}), status {', '.join(row['fold_status'])}; nested CV {s['nested_cv']:.0f} s wall "
            f"({s['nested_cv_cpu']:.0f} s CPU); baseline matrices "
            + ", ".join(f"{m} {s[m]:.2g} s" for m in ("ted", "qed", "fc_srvf", "tmd"))
            + "."
        )
    if "learn_53" in results:
        r = results["learn_53"]
        w = r["weights"]
        lines += [
            "",
            f"**Time to learn λ on the bundled 53 roots** (T = {a['T']}, `learn_weights` with its "
            "first registration at the paper's λ; first in its process, so compilation is included): "
            f"**{r['wall_s']:.0f} s wall**, {r['cpu_s']:.0f} s process CPU time; "
            f"{r['n_reregistrations']} re-registrations (at most {r['max_reregistrations']}) of all 1,378 pairs, "
            f"pairs whose lateral correspondence changed per re-registration {r.get('changed_pairs')}, "
            f"{r['steps']} BFGS steps, 1-min load {r.get('load_before') or float('nan'):.1f} before and "
            f"{r.get('load_after', float('nan')):.1f} after, "
            f"status {r['status']}; λ = main {w['main']:.3g}, lateral {w['lateral']:.3g}, position "
            f"{w['position']:.3g}; loss at registered distances "
            + " → ".join(f"{x:.4f}" for x in r["loss_trace"])
            + ".",
        ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
