"""FK throughput: hybrid_pk ``Robot.fk`` vs raw pytorch-kinematics vs a pinocchio loop.

All three run in the same process on the same URDF and the same joint values, in
interleaved rounds (so a noisy neighbour slows all of them alike); the median of
the rounds is reported with the ratios against our ``Robot.fk``.

    python bench/fk.py                      # rx160, batches 1 / 1k / 10k / 100k
    python bench/fk.py --robot ur10 --rounds 7 --grad
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch

import hybrid_pk as hpk
from tests.oracles.pk_chain import pk_chain


def _time(fn: Callable[[], object], budget_s: float) -> float:
    """Seconds per call, repeating ``fn`` for about ``budget_s``."""
    fn()
    n, start = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        elapsed = time.perf_counter() - start
        if elapsed >= budget_s:
            return elapsed / n


def _pinocchio_loop(robot: hpk.Robot):
    try:
        import pinocchio as pin
    except ImportError:
        return None
    model = pin.buildModelFromUrdf(robot.spec.urdf_path)
    data = model.createData()
    fid = model.getFrameId(robot.end_link)
    idx = [model.idx_qs[model.getJointId(n)] for n in robot.joint_names]

    def run(q: np.ndarray) -> None:
        full = np.zeros(model.nq)
        for qi in q:
            full[idx] = qi
            pin.framesForwardKinematics(model, data, full)
            data.oMf[fid].homogeneous  # noqa: B018 - read the result like a user would

    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--robot", default="rx160", help="shipped robot name or URDF path")
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 1000, 10_000, 100_000])
    ap.add_argument("--dtypes", nargs="+", default=["float32", "float64"])
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds (median reported)")
    ap.add_argument("--budget", type=float, default=0.2, help="seconds per measurement")
    ap.add_argument("--grad", action="store_true", help="time with autograd on (q requires grad)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--pin-max-batch", type=int, default=10_000, help="skip the slow loop above")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    robot = hpk.Robot.from_urdf(args.robot)
    pin_run = _pinocchio_loop(robot)
    print(
        f"robot {robot.name} ({robot.dof} dof, end link {robot.end_link}); "
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, "
        f"autograd {'on' if args.grad else 'off'}; median of {args.rounds} rounds"
    )
    header = f"{'dtype':8} {'batch':>7} {'ours us':>11} {'pk us':>11} {'pin us':>11} "
    header += f"{'pk/ours':>8} {'pin/ours':>9}"
    print(header)
    print("-" * len(header))
    for dtype_name in args.dtypes:
        dtype = getattr(torch, dtype_name)
        chain = pk_chain(robot, dtype)
        for batch in args.batches:
            q = robot.sample_q(batch, torch.Generator().manual_seed(0)).to(dtype)
            q.requires_grad_(args.grad)
            q_np = q.detach().to(torch.float64).numpy()

            def ours(q=q):
                return robot.fk(q)

            def pk(q=q, chain=chain):
                return chain.forward_kinematics(q, end_only=True).get_matrix()

            # Same answer before timing anything.
            with torch.no_grad():
                err = (ours().double() - pk().double()).abs().max().item()
            # pytorch-kinematics parses URDF origins in float32, so even its float64
            # chain is only float32-accurate (hybrid_pk keeps the URDF's digits).
            tol = 1e-4 if dtype == torch.float32 else 1e-6
            assert err < tol, f"ours and pytorch-kinematics disagree by {err:.2e}"

            use_pin = pin_run is not None and batch <= args.pin_max_batch
            rows: dict[str, list[float]] = {"ours": [], "pk": [], "pin": []}
            ctx = torch.enable_grad() if args.grad else torch.no_grad()
            with ctx:
                for _ in range(args.rounds):
                    rows["ours"].append(_time(ours, args.budget))
                    rows["pk"].append(_time(pk, args.budget))
                    if use_pin:
                        rows["pin"].append(_time(lambda q_np=q_np: pin_run(q_np), args.budget))
            med = {k: statistics.median(v) if v else float("nan") for k, v in rows.items()}
            print(
                f"{dtype_name:8} {batch:>7} {med['ours'] * 1e6:>11.1f} {med['pk'] * 1e6:>11.1f} "
                f"{med['pin'] * 1e6:>11.1f} {med['pk'] / med['ours']:>8.2f} "
                f"{med['pin'] / med['ours']:>9.2f}"
            )
    print("ratios > 1: hybrid_pk is that many times faster than the peer.")


if __name__ == "__main__":
    main()
