"""Which layout for which job: batch-first vs batch-last evaluation of one chain.

Both layouts evaluate the same chain constants (``Robot.chain_terms``). Timed in
interleaved rounds on the same joint values (median reported):

- pose only: the balanced tree of 4×4 products (``Robot.fk`` with derivatives, and
  below ``ALIGNED_MIN_BATCH`` configurations) vs the z-aligned batch-last chain
  (``aligned.aligned_fk``: ``Robot.fk`` without derivatives from ``ALIGNED_MIN_BATCH`` on);
- pose + Jacobian: batch-first frames (one 4×4 product per joint, then ``z × (p - o)``)
  vs ``pose_jacobian_batch_last`` (``Robot.jacobian``) and the z-aligned IK kernel
  (``ChainKernel``, float64), and pytorch-kinematics' ``SerialChain.jacobian`` as the peer.

The library uses the faster layout of each job; the ratios > 1 say by how much.

    python bench/fk_layouts.py                      # rx160, float64, batches 1 .. 100k
    python bench/fk_layouts.py --robot ur10 --dtype float32 --threads 2
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch

import hybrid_pk as hpk
from hybrid_pk.robot.aligned import AlignedFK, aligned_fk
from hybrid_pk.robot.chain import (
    batch_last_terms,
    local_transforms,
    pose_jacobian_batch_last,
    product,
)
from hybrid_pk.robot.kernel import ChainKernel
from tests.oracles.pk_chain import pk_chain


def _time(fn: Callable[[], object], budget_s: float) -> float:
    fn()
    n, start = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        elapsed = time.perf_counter() - start
        if elapsed >= budget_s:
            return elapsed / n


def _pose_tree(robot: hpk.Robot, q: torch.Tensor) -> torch.Tensor:
    """``Robot.fk``'s balanced product of the local transforms."""
    terms = robot._terms(None, q.dtype, fold_tip=True)
    return product(local_transforms(q, terms, robot.chain_revolute))


def _pose_aligned(robot: hpk.Robot, aligned: AlignedFK, q: torch.Tensor) -> torch.Tensor:
    C = aligned.constants(robot.chain_terms(torch.float64), q.dtype)
    return aligned_fk(C, q, robot.chain_revolute, aligned.all_revolute)


def _jacobian_batch_first(robot: hpk.Robot, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pose and Jacobian from batch-first frames (the alternative to batch last)."""
    frames = robot.link_frames(q)
    n = robot.chain_dof
    a = robot.chain_terms(q.dtype).axis
    z = (frames[..., :n, :3, :3] @ a[..., None])[..., 0]
    v = torch.linalg.cross(z, frames[..., n : n + 1, :3, 3] - frames[..., :n, :3, 3])
    return frames[..., n, :, :], torch.cat([v, z], -1).transpose(-1, -2)


def _jacobian_batch_last(robot: hpk.Robot, q: torch.Tensor):
    C = batch_last_terms(robot.chain_terms(q.dtype))
    return pose_jacobian_batch_last(C, q.T, robot.chain_revolute)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--robot", default="rx160", help="shipped robot name or URDF path")
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 10, 100, 1000, 10_000, 100_000])
    ap.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds (median reported)")
    ap.add_argument("--budget", type=float, default=0.1, help="seconds per measurement")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    robot = hpk.Robot.from_urdf(args.robot)
    if robot.has_mimic or not bool(robot.chain_revolute.all()):
        raise SystemExit("this benchmark compares all-revolute chains without mimic joints")
    chain = pk_chain(robot, dtype)
    print(
        f"robot {robot.name} ({robot.dof} dof), {args.dtype}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads, no autograd; median of {args.rounds} rounds [us]"
    )
    aligned, kernel = AlignedFK(robot.chain_revolute), ChainKernel(robot)
    header = f"{'batch':>7} {'fk tree':>9} {'fk align':>9} {'tree/align':>10}   "
    header += f"{'J first':>9} {'J last':>9} {'J kernel':>9} {'J pk':>9} {'first/last':>10} "
    header += f"{'last/kernel':>11} {'pk/kernel':>9}"
    print(header)
    print("-" * len(header))
    for batch in args.batches:
        q = robot.sample_q(batch, torch.Generator().manual_seed(0)).to(dtype)
        qt64 = q.double().T.contiguous()
        jobs = {
            "fk tree": lambda q=q: _pose_tree(robot, q),
            "fk align": lambda q=q: _pose_aligned(robot, aligned, q),
            "J first": lambda q=q: _jacobian_batch_first(robot, q),
            "J last": lambda q=q: _jacobian_batch_last(robot, q),
            "J kernel": lambda qt=qt64: kernel.soa(qt),
            "J pk": lambda q=q: chain.jacobian(q),
        }
        with torch.no_grad():
            T_tree = _pose_tree(robot, q)
            assert float((_pose_aligned(robot, aligned, q) - T_tree).abs().max()) < 1e-4
            J_first = _jacobian_batch_first(robot, q)[1]
            J_last = _jacobian_batch_last(robot, q)[2].permute(2, 0, 1)
            assert float((J_first - J_last).abs().max()) < 1e-4
            rows: dict[str, list[float]] = {k: [] for k in jobs}
            for _ in range(args.rounds):
                for k, fn in jobs.items():
                    rows[k].append(_time(fn, args.budget) * 1e6)
        med = {k: statistics.median(v) for k, v in rows.items()}
        print(
            f"{batch:>7} {med['fk tree']:>9.1f} {med['fk align']:>9.1f} "
            f"{med['fk tree'] / med['fk align']:>10.2f}   {med['J first']:>9.1f} "
            f"{med['J last']:>9.1f} {med['J kernel']:>9.1f} {med['J pk']:>9.1f} "
            f"{med['J first'] / med['J last']:>10.2f} {med['J last'] / med['J kernel']:>11.2f} "
            f"{med['J pk'] / med['J kernel']:>9.2f}"
        )
    print("tree/align > 1: the aligned chain is faster for the pose; first/last > 1: batch")
    print("last is faster for the Jacobian; last/kernel, pk/kernel > 1: the IK kernel is faster")
    print("(the kernel works in float64 whatever --dtype).")


if __name__ == "__main__":
    main()
