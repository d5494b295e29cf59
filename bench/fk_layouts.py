"""Which layout for which job: batch-first vs batch-last evaluation of one chain.

Both layouts evaluate the same chain constants (``Robot.chain_terms``). Timed in
interleaved rounds on the same joint values (median reported):

- pose only: ``Robot.fk`` (batch first, balanced tree of 4×4 products) vs a
  batch-last pose loop (3×3 blocks as ``(3, 3, M)`` tensors, one joint after another);
- pose + Jacobian: batch-first frames (one 4×4 product per joint, then ``z × (p - o)``)
  vs ``pose_jacobian_batch_last`` (what ``Robot.jacobian`` and the IK kernel use),
  and pytorch-kinematics' ``SerialChain.jacobian`` as the peer.

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
from hybrid_pk.geometry.batch_last import compose, rotate
from hybrid_pk.robot.chain import batch_last_terms, pose_jacobian_batch_last
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


def _pose_batch_last(robot: hpk.Robot, q: torch.Tensor) -> torch.Tensor:
    """The pose alone in batch-last layout (the alternative to ``Robot.fk``)."""
    C = batch_last_terms(robot.chain_terms(q.dtype))
    qt = q.T
    R_loc = torch.addcmul(torch.addcmul(C.R[0], torch.sin(qt), C.R[1]), 1 - torch.cos(qt), C.R[2])
    R, p = R_loc[:, :, 0], C.t[:, 0].expand(3, qt.shape[1])
    for i in range(1, qt.shape[0]):
        p = p + rotate(R, C.t[:, i])
        R = compose(R, R_loc[:, :, i])
    T = q.new_zeros(q.shape[0], 4, 4)
    T[:, :3, :3] = compose(R, C.R_tip).permute(2, 0, 1)
    T[:, :3, 3] = (p + rotate(R, C.t_tip)).T
    T[:, 3, 3] = 1
    return T


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
    header = f"{'batch':>7} {'fk tree':>9} {'fk last':>9} {'last/tree':>9}   "
    header += f"{'J first':>9} {'J last':>9} {'J pk':>9} {'first/last':>10} {'pk/last':>8}"
    print(header)
    print("-" * len(header))
    for batch in args.batches:
        q = robot.sample_q(batch, torch.Generator().manual_seed(0)).to(dtype)
        jobs = {
            "fk tree": lambda q=q: robot.fk(q),
            "fk last": lambda q=q: _pose_batch_last(robot, q),
            "J first": lambda q=q: _jacobian_batch_first(robot, q),
            "J last": lambda q=q: _jacobian_batch_last(robot, q),
            "J pk": lambda q=q: chain.jacobian(q),
        }
        with torch.no_grad():
            T_last = _pose_batch_last(robot, q)
            assert float((T_last - robot.fk(q)).abs().max()) < 1e-4
            J_first = _jacobian_batch_first(robot, q)[1]
            J_last = _jacobian_batch_last(robot, q)[2].permute(2, 0, 1)
            assert float((J_first - J_last).abs().max()) < 1e-4
            rows: dict[str, list[float]] = {k: [] for k in jobs}
            for _ in range(args.rounds):
                for k, fn in jobs.items():
                    rows[k].append(_time(fn, args.budget) * 1e6)
        med = {k: statistics.median(v) for k, v in rows.items()}
        print(
            f"{batch:>7} {med['fk tree']:>9.1f} {med['fk last']:>9.1f} "
            f"{med['fk last'] / med['fk tree']:>9.2f}   {med['J first']:>9.1f} "
            f"{med['J last']:>9.1f} {med['J pk']:>9.1f} {med['J first'] / med['J last']:>10.2f} "
            f"{med['J pk'] / med['J last']:>8.2f}"
        )
    print("last/tree > 1: the tree is faster for the pose; first/last > 1: batch last is")
    print("faster for the Jacobian; pk/last > 1: faster than pytorch-kinematics' jacobian.")


if __name__ == "__main__":
    main()
