"""Replica-steps per second of the batched torch time loop against the DOLFINx/PETSc and C paths.

Two grids, each in one run beside its baseline (one process, one thread each):

- the report's 60 x 60 grid, implicit scheme: ``BatchedMonodomain`` with B = 1, 8, 64, 512
  replicas against ``MonodomainMitchellSchaeffer`` (PETSc CG + ICC, C right-hand side), one
  replica; goal: B = 64 >= 4x the replica-steps (hence decisions) per second of the PETSc path;
- the resolved 1000 x 1000 grid, explicit scheme: B = 1, 8 against the compiled C pass of
  ``MonodomainMitchellSchaeffer(scheme="explicit")``; goal: per replica-step within 1.5x of it.

Each torch row runs eager (float64) and through ``torch.compile`` (``compiled=True``; float64,
and float32 for the report's grid); the compilation is done before the clock starts.

With ``--device cuda`` the torch rows run on the GPU (float32, eager and compiled; the
baselines stay on one CPU core), and the goals are the GPU's:

- 60 x 60, implicit: B = 1024 replicas >= 2,000 decisions per second (a decision is
  ``decision_interval`` / dt = 1667 steps of the ATP task);
- 1000 x 1000, explicit: >= 50% of the memory-bandwidth roofline, the rate at which the GPU could
  move the stencil step's least traffic (read u and w, write u and w: 4 n values per
  replica-step) at the bandwidth of a device-to-device copy measured in the same run (the floor)
  or the card's specified peak, whichever is higher.

The state is a front running into resting tissue (u = 1 on x < -40, w = 1): the work per step
does not depend on it, except the CG iterations (counted). Writes
benchmarks/results/batched-<device>.txt with the command and load average.

    python benchmarks/batched.py [--replicas 1 8 64 512] [--resolved-replicas 1 8] [--steps 20]
    python benchmarks/batched.py --device cuda --replicas 1 64 1024 4096 --resolved-replicas 1 8 32
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import physicsrl.fem  # noqa: F401  (first: loads the MPI library)

# isort: split

import torch
from bench_run import at_least  # benchmarks/ (the script's directory)
from mpi4py import MPI

from physicsrl.coordinated import Coordinator
from physicsrl.envs.atp import ATPConfig, MSModel
from physicsrl.envs.task import SquareMesh
from physicsrl.fem import MonodomainMitchellSchaeffer
from physicsrl.fem.batched import BatchedMonodomain

PEAK_BANDWIDTH = {"H100 80GB HBM3": 3.35e12, "H200": 4.8e12}
"""Specified memory bandwidth (bytes/s) of the GPUs by a substring of their torch name."""


def front(x):
    return (x[0] < -40.0).astype(float)


def reference_rate(domain, scheme: str, steps: int) -> float:
    """Steps per second of the DOLFINx path on one replica (after one warm-up step)."""
    ms = MonodomainMitchellSchaeffer(Coordinator(MPI.COMM_SELF), domain, u0=front, scheme=scheme)
    with ms.coordinator:
        ms.advance_time(ms.dt)
        start = time.perf_counter()
        ms.advance_time(steps * ms.dt)
        return steps / (time.perf_counter() - start)


def batched_rate(domain, scheme: str, replicas: int, steps: int, device: str, **settings):
    """(replica-steps per second, CG iterations per step) of the torch loop; ``settings``:
    ``compiled`` and ``dtype`` of ``BatchedMonodomain``."""
    model = {**MSModel().numerics(), "scheme": scheme}
    torch._dynamo.reset()  # each row compiles its own step, within dynamo's recompile limit
    sim = BatchedMonodomain(domain, **model, device=device, **settings)
    u = sim.nodal(front).expand(replicas, -1).clone()
    w = torch.ones_like(u)
    sim.advance(u, w, None, 2)
    if device == "cuda":
        torch.cuda.synchronize()
    iterations = sim.iterations
    start = time.perf_counter()
    sim.advance(u, w, None, steps)
    if device == "cuda":
        torch.cuda.synchronize()
    elapsed = time.perf_counter() - start
    return replicas * steps / elapsed, (sim.iterations - iterations) / steps


def copy_bandwidth(megabytes: int = 1024) -> float:
    """Bytes per second (read + written) of a device-to-device copy on the GPU: the floor."""
    x = torch.empty(megabytes * 2**20 // 4, device="cuda")
    y = torch.empty_like(x)
    y.copy_(x)
    torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(20):
        y.copy_(x)
    torch.cuda.synchronize()
    return 20 * 2 * x.numel() * 4 / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--replicas", type=at_least(1), nargs="+", default=[1, 8, 64, 512])
    parser.add_argument("--resolved-replicas", type=at_least(1), nargs="+", default=[1, 8])
    parser.add_argument("--steps", type=at_least(1), default=20)
    parser.add_argument("--resolved-cells", type=at_least(2), default=1000)
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    args = parser.parse_args()
    torch.set_num_threads(1)
    lines = [
        "command: python " + " ".join(sys.argv),
        f"load average before: {os.getloadavg()[0]:.2f} ({os.cpu_count()} cores)",
        f"device: {args.device}; one process, torch threads 1",
    ]

    def report(line: str) -> None:
        print(line, flush=True)
        lines.append(line)

    for line in lines:
        print(line)
    goals = []
    gpu = args.device == "cuda"
    if gpu:
        variants = {
            "eager float32": {"dtype": "float32"},
            "compiled float32": {"compiled": True, "dtype": "float32"},
        }
        gpu_name = torch.cuda.get_device_name()
        bandwidth = copy_bandwidth()
        peak = next((v for k, v in PEAK_BANDWIDTH.items() if k in gpu_name), None)
        roofline = max(bandwidth, peak or 0.0)
        report(
            f"GPU: {gpu_name}; device-to-device copy {bandwidth / 1e12:.2f} TB/s (read + written); "
            f"specified peak {'unknown' if peak is None else f'{peak / 1e12:.2f} TB/s'}; "
            f"roofline {roofline / 1e12:.2f} TB/s"
        )
    else:
        variants = {
            "eager float64": {},
            "compiled float64": {"compiled": True},
            "compiled float32": {"compiled": True, "dtype": "float32"},
        }
    steps_per_decision = round(ATPConfig().decision_interval / MSModel().dt)
    report("\n60 x 60, implicit (report's scheme)")
    domain = SquareMesh(60, 50.0, "quadrilateral").create(MPI.COMM_SELF)
    petsc = reference_rate(domain, "implicit", args.steps * 5)
    report(f"  PETSc path, 1 replica: {petsc:10.0f} replica-steps/s")
    for name, settings in variants.items():
        for B in args.replicas:
            rate, iterations = batched_rate(
                domain, "implicit", B, args.steps, args.device, **settings
            )
            decisions = rate / steps_per_decision
            report(
                f"  torch {name}, B = {B:4d}: {rate:8.0f} replica-steps/s, {decisions:7.1f} "
                f"decisions/s ({rate / petsc:.2f}x PETSc, {iterations:.1f} CG iterations per step)"
            )
            if B == 64 and not gpu:
                goals.append((f"60 x 60 implicit, B = 64 >= 4x PETSc ({name})", rate / petsc >= 4))
            if B == 1024 and gpu:
                goals.append(
                    (f"60 x 60 implicit, B = 1024 >= 2000 decisions/s ({name})", decisions >= 2000)
                )

    n = args.resolved_cells
    report(f"\n{n} x {n}, explicit")
    domain = SquareMesh(n, 50.0, "quadrilateral").create(MPI.COMM_SELF)
    compiled = reference_rate(domain, "explicit", args.steps)
    report(f"  compiled C path, 1 replica: {compiled:8.1f} replica-steps/s")
    traffic = 4 * (n + 1) ** 2 * 4  # bytes per replica-step in float32: u, w read and written
    for name in list(variants)[:2]:
        best = 0.0
        for B in args.resolved_replicas:
            rate, _ = batched_rate(domain, "explicit", B, args.steps, args.device, **variants[name])
            line = (
                f"  torch {name}, B = {B:4d}: {rate:8.1f} replica-steps/s ({rate / compiled:.2f}x C"
            )
            if gpu:
                line += f", {rate * traffic / roofline:.0%} of the roofline"
            report(line + ")")
            best = max(best, rate)
        if gpu:
            goals.append(
                (
                    f"{n} x {n} explicit, >= 50% of the bandwidth roofline ({name})",
                    best * traffic >= 0.5 * roofline,
                )
            )
        else:
            goals.append(
                (
                    f"{n} x {n} explicit, within 1.5x of C per replica-step ({name})",
                    best >= compiled / 1.5,
                )
            )
    if not gpu:
        report("\nGPU rows: python benchmarks/batched.py --device cuda (on a machine with one)")
    report(f"load average after: {os.getloadavg()[0]:.2f}")
    for name, met in goals:
        report(f"goal {'met' if met else 'MISSED'}: {name}")
    out = Path(__file__).parent / "results" / f"batched-{args.device}.txt"
    out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
