"""Distance matrix on a Dask LocalCluster (issue 8): pairs/s with 1 and 2 worker processes
against the in-process path, and a projection for N = 5,000 roots on 100 cluster cores.

    python benchmarks/bench_dask.py [--quick] [--n N] [--x64] [--devices D]

Data: `synthetic_roots` in the default data set's proportions (control, drought, high_nitrate),
T = 100, K = 2 × most laterals, scale-normalised, float32 unless --x64. The in-process path uses
`D` XLA devices (default: every core); each worker is one process with one XLA device and one
thread. Compile time is reported separately: the in-process program is compiled on a 2-root
batch of the same capacities, and every worker is warmed up with one block before timing.
Worker CPU seconds (psutil, summed over workers) give the per-pair cost used by the projection.
Writes benchmarks/results/dask.json (dask_quick.json with --quick) and prints a markdown table.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _common import machine, setup_jax, write_json  # noqa: E402

PROJECT_N = 5000
PROJECT_CORES = 100


def _cpu_seconds():
    import psutil

    t = psutil.Process().cpu_times()
    return t.user + t.system


def _roots(n: int):
    from rootshape_jax.datasets import DEFAULT_COMPOSITION, synthetic_roots

    total = sum(DEFAULT_COMPOSITION.values())
    counts = {c: n * k // total for c, k in DEFAULT_COMPOSITION.items()}
    counts["control"] += n - sum(counts.values())
    roots = []
    for condition, k in counts.items():
        roots.extend(synthetic_roots(k, condition=condition, seed=2023))
    return roots


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--quick", action="store_true", help="N = 20, for a smoke run")
    p.add_argument("--n", type=int, default=200, help="number of roots (default 200)")
    p.add_argument("--x64", action="store_true", help="float64 (default float32)")
    p.add_argument("--devices", type=int, default=None, help="XLA devices of the in-process path")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    args = p.parse_args(argv)
    n = 20 if args.quick else args.n
    jax = setup_jax(args.devices, x64=args.x64)
    import distributed
    import numpy as np

    import rootshape_jax as rs
    from rootshape_jax import _dask, _pairwise

    T, chunk = 100, 32
    pairs = n * (n - 1) // 2
    # The library's default block (8 chunks), smaller when needed to give every worker >= 4 blocks.
    block = chunk * max(1, min(8, pairs // (chunk * 4 * max(args.workers))))
    w = rs.Weights()
    roots = _roots(n)
    trees = rs.batch(roots, n_points=T, normalise_scale=True)
    K = trees.capacity
    lat = [r.n_laterals for r in roots]
    print(
        f"N = {n} roots ({pairs} pairs), T = {T}, K = {K}, laterals per root {min(lat)}–{max(lat)} "
        f"(mean {np.mean(lat):.1f}), {'float64' if args.x64 else 'float32'}",
        flush=True,
    )
    out = {
        "machine": machine(),
        "dtype": "float64" if args.x64 else "float32",
        "n_roots": n,
        "pairs": pairs,
        "T": T,
        "K": K,
        "chunk_size": chunk,
        "block_size": block,
        "mean_laterals": float(np.mean(lat)),
    }

    # In-process path: compile on 2 roots (same chunk shape), then the whole matrix.
    small = jax.tree.map(lambda x: x[:2], trees)
    t0 = time.perf_counter()
    rs.pairwise_distances(small, weights=w, chunk_size=chunk, progress=False)
    compile_s = time.perf_counter() - t0
    c0, t0 = _cpu_seconds(), time.perf_counter()
    D_local, stats = rs.pairwise_distances(trees, weights=w, chunk_size=chunk, progress=True, return_stats=True)
    D_local = np.asarray(jax.block_until_ready(D_local))
    wall = time.perf_counter() - t0
    cpu = _cpu_seconds() - c0
    out["in_process"] = dict(
        devices=len(jax.devices()),
        compile_plus_first_chunk_s=compile_s,
        wall_s=wall,
        pairs_per_s=pairs / wall,
        cpu_s=cpu,
        cpu_s_per_pair=cpu / pairs,
        lateral_dp=stats["lateral_dp"],
    )
    print(
        f"in-process ({len(jax.devices())} devices): {wall:.1f} s, {pairs / wall:.2f} pairs/s, "
        f"compile {compile_s:.1f} s",
        flush=True,
    )

    # Warm-up block: the first chunk-sized block of the real pairs.
    opts = jax.tree.map(np.asarray, rs.RegistrationOptions())
    w_np = jax.tree.map(np.asarray, w)
    I, J = np.triu_indices(n, 1)
    s_np = jax.tree.map(np.asarray, rs.to_srvf(trees))
    x64 = bool(jax.config.read("jax_enable_x64"))

    out["dask"] = []
    for n_workers in args.workers:
        with (
            distributed.LocalCluster(
                n_workers=n_workers, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
            ) as cluster,
            distributed.Client(cluster) as client,
        ):
            client.wait_for_workers(n_workers)
            addrs = sorted(client.scheduler_info()["workers"])
            [s_fut] = client.scatter([s_np], broadcast=True, hash=False)
            t0 = time.perf_counter()
            block = (I[:chunk], J[:chunk])
            warm = [
                client.submit(
                    _dask._task,
                    _pairwise.pair_block,
                    x64,
                    block,
                    (s_fut, s_fut, w_np, opts, chunk),
                    workers=[a],
                    allow_other_workers=False,
                    pure=False,
                )
                for a in addrs
            ]
            client.gather(warm)
            warm_s = time.perf_counter() - t0
            del warm, s_fut
            cpu0 = sum(client.run(_cpu_seconds).values())
            t0 = time.perf_counter()
            D, st = rs.pairwise_distances(
                trees, weights=w, chunk_size=chunk, progress=True, return_stats=True, client=client, block_size=block
            )
            D = np.asarray(D)
            wall = time.perf_counter() - t0
            cpu = sum(client.run(_cpu_seconds).values()) - cpu0
        row = dict(
            workers=n_workers,
            warmup_compile_s=warm_s,
            wall_s=wall,
            pairs_per_s=pairs / wall,
            worker_cpu_s=cpu,
            cpu_s_per_pair=cpu / pairs,
            blocks=st["blocks"],
            speed_vs_in_process=out["in_process"]["wall_s"] / wall,
            max_abs_diff_vs_in_process=float(np.max(np.abs(D - D_local))),
            bitwise_equal_to_in_process=bool(np.array_equal(D, D_local)),
        )
        out["dask"].append(row)
        print(
            f"dask {n_workers} worker(s): {wall:.1f} s, {pairs / wall:.2f} pairs/s "
            f"({row['speed_vs_in_process']:.2f}× in-process), warm-up/compile {warm_s:.1f} s, "
            f"worker CPU {cpu / pairs * 1e3:.1f} ms/pair, max |ΔD| {row['max_abs_diff_vs_in_process']:.2e}",
            flush=True,
        )

    # Projection: N = 5,000 on 100 cores, from the one-worker run's cost per pair.
    one = next((r for r in out["dask"] if r["workers"] == 1), out["dask"][0])
    two = next((r for r in out["dask"] if r["workers"] == 2), None)
    per_pair = one["wall_s"] / pairs * one["workers"]  # core-seconds per pair (one worker = one core)
    eff = two["pairs_per_s"] / (2 * one["pairs_per_s"]) if two else None
    big = PROJECT_N * (PROJECT_N - 1) // 2
    ideal = big * per_pair / PROJECT_CORES
    proj = dict(
        n_roots=PROJECT_N,
        pairs=big,
        cores=PROJECT_CORES,
        core_s_per_pair=per_pair,
        ideal_wall_h=ideal / 3600,
        measured_two_worker_efficiency=eff,
        wall_h_at_measured_efficiency=(ideal / eff / 3600) if eff else None,
        tasks=-(-big // (8 * chunk)),
        compile_s_per_worker=one["warmup_compile_s"],
        assumptions=[
            "cost per pair as measured with one worker process (one XLA device, one thread) here",
            "cluster cores as fast as this machine's; 100 single-core worker processes",
            f"roots like this data set (T = {T}, K = {K}, laterals per root as in the default data "
            "set); the cost per pair does not depend on N",
            "scheduler overhead and result transfer small against blocks of "
            f"{8 * chunk} pairs (one task each); compile once per worker, in parallel",
        ],
    )
    out["projection"] = proj

    name = "dask_quick" if args.quick else "dask"
    path = write_json(name, out)
    m = out["machine"]
    lines = [
        f"Distance matrix on Dask ({m['cpu']}, {m['cores']} cores, {out['dtype']}): N = {n} roots, "
        f"{pairs} pairs, T = {T}, K = {K}.",
        "",
        "| path | wall (s) | pairs/s | vs in-process | compile / warm-up (s) | CPU ms / pair |",
        "|---|---:|---:|---:|---:|---:|",
        f"| in-process, {out['in_process']['devices']} XLA devices | {out['in_process']['wall_s']:.1f} | "
        f"{out['in_process']['pairs_per_s']:.2f} | 1.00× | {compile_s:.1f} | "
        f"{out['in_process']['cpu_s_per_pair'] * 1e3:.1f} |",
    ]
    for r in out["dask"]:
        lines.append(
            f"| Dask LocalCluster, {r['workers']} worker(s) | {r['wall_s']:.1f} | {r['pairs_per_s']:.2f} | "
            f"{r['speed_vs_in_process']:.2f}× | {r['warmup_compile_s']:.1f} | {r['cpu_s_per_pair'] * 1e3:.1f} |"
        )
    lines += [
        "",
        f"Projection, N = {PROJECT_N:,} ({big:,} pairs) on {PROJECT_CORES} cores: "
        f"{per_pair * 1e3:.0f} core-ms per pair → {proj['ideal_wall_h']:.1f} h at perfect scaling"
        + (
            f", {proj['wall_h_at_measured_efficiency']:.1f} h at the 2-worker efficiency measured here ({eff:.0%})"
            if eff
            else ""
        )
        + f"; {proj['tasks']:,} tasks of {8 * chunk} pairs.",
    ]
    table = "\n".join(lines)
    print(table)
    (path.parent / f"{name}.md").write_text(table + "\n")
    print("wrote", path)


if __name__ == "__main__":
    main()
