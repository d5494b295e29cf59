"""IK bench: hybrid_pk ``solve_ik`` vs pytorch-kinematics ``PseudoInverseIK`` (and TRAC-IK).

Same targets (FK of random joint values within the limits), same start configurations
(the quasi-random seeds of ``solve_ik``) and the same iteration budget for both batched
solvers; TRAC-IK (``pytracik``, if installed) gets one call per seed with a per-call
timeout. Reported per robot and solver:

- time per target [ms] (median of ``--rounds``, solvers interleaved), wall clock and
  this process's CPU time (on a machine shared with other jobs the wall time grows
  with their load, the CPU time much less),
- success: targets with at least one solution within ``--tol-mm`` / ``--tol-deg``,
  checked here with our FK whatever the solver claims, and within the joint limits,
- coverage: analytic branches within the limits (EAIK) matched by a solution,
- the speed ratio pytorch-kinematics / ours;
- our evaluations (configurations whose pose and Jacobian were computed, the polish
  included): the work, which does not move with the machine's load.

Then the shape of the paper's Table IV: errors w.r.t. an expensive model (a calibrated
RX160 with a joint offset, a link error and joint compliance; a UR10 with a smooth
residual from a small fixed MLP, mm / mrad scale) of the two-stage solver and of
Wang et al.'s one-shot correction, on FK targets of that model.

    python bench/ik.py                        # ur10 + rx160, 200 targets, 64 seeds
    python bench/ik.py --targets 50 --no-tracik --no-hybrid
    python bench/ik.py --targets 50 --no-tracik --no-hybrid --wrist-near-zero

``--wrist-near-zero``: the fifth joint of every target (UR10 wrist_2, RX160 joint_5)
within 1e-5..1e-3 rad of 0 (log-uniform, either sign), a wrist near its singular
configuration, where solutions converge slowly and are polished onto their branch.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import numpy as np
import torch

import hybrid_pk as hpk
from hybrid_pk.effects import ExtendedModel, make_effect
from hybrid_pk.evaluation.metrics import pose_error
from hybrid_pk.geometry import so3_exp, transform
from hybrid_pk.ik import IKOptions, solve_ik, solve_ik_two_stage, wang_baseline
from hybrid_pk.ik.dedup import distinct_mask
from hybrid_pk.ik.seeds import quasi_random_seeds
from tests.oracles.eaik_oracle import branch_coverage, eaik_branches
from tests.oracles.pk_chain import pk_chain


def _verified(robot: hpk.Robot, T: torch.Tensor, q: torch.Tensor, ok: torch.Tensor, args):
    """Per target: distinct solutions among ``q (N, S, dof)`` (``ok`` claimed) that pass
    our FK check, limits included."""
    lo, hi = robot.joint_limits
    with torch.no_grad():
        err = pose_error(T[:, None].expand(-1, q.shape[1], 4, 4), robot.fk(q))
    good = ok & torch.isfinite(q).all(-1) & (q >= lo).all(-1) & (q <= hi).all(-1)
    good &= (err.position_mm <= args.tol_mm) & (err.orientation_deg <= args.tol_deg)
    keep = distinct_mask(q, good, err.position_mm.nan_to_num(math.inf), robot.revolute)
    return [q[i][keep[i]].numpy() for i in range(q.shape[0])]


_WORK: dict[str, int] = {}  # evaluations (pose + Jacobian) of our last call, per robot


def _ours(robot, T, seeds, args):
    res = solve_ik(robot, T, seeds=seeds, options=IKOptions(max_iterations=args.iterations))
    _WORK[robot.name] = res.info["evaluations"]  # the same every round: the work, not the time
    return [res.solutions(i).numpy() for i in range(T.shape[0])]


def _pk(robot, T, seeds, args):
    import pytorch_kinematics as pk

    ik = pk.PseudoInverseIK(
        pk_chain(robot),
        retry_configs=seeds,
        joint_limits=torch.stack(robot.joint_limits, -1),
        max_iterations=args.iterations,
        pos_tolerance=args.tol_mm * 1e-3,
        rot_tolerance=math.radians(args.tol_deg),
    )
    sol = ik.solve(pk.Transform3d(matrix=T))
    return _verified(robot, T, sol.solutions.detach(), sol.converged, args)


def _tracik(robot, T, seeds, args):
    from trac_ik import TracIK

    solver = TracIK(
        robot.root_link,
        robot.end_link,
        robot.spec.urdf_path,
        timeout=args.tracik_timeout,
        epsilon=args.tol_mm * 1e-3,
    )
    n, s = T.shape[0], seeds.shape[0]
    q = torch.full((n, s, robot.dof), math.nan, dtype=torch.float64)
    Tn = T.numpy()
    for i in range(n):
        for j in range(s):
            out = solver.ik(Tn[i, :3, 3], Tn[i, :3, :3], seeds[j].numpy())
            if out is not None:
                q[i, j] = torch.as_tensor(np.asarray(out, dtype=np.float64))
    return _verified(robot, T, q, torch.isfinite(q).all(-1), args)


class SmoothResidual(torch.nn.Module):
    """Nominal FK times a q-dependent twist from a fixed random MLP (mm / mrad scale)."""

    def __init__(self, robot: hpk.Robot) -> None:
        super().__init__()
        self._robot = (robot,)  # not a submodule: its parameters are not ours to set
        gen = torch.Generator().manual_seed(0)
        self.l1 = torch.nn.Linear(robot.dof, 32, dtype=torch.float64)
        self.l2 = torch.nn.Linear(32, 6, dtype=torch.float64)
        with torch.no_grad():
            for p in (*self.l1.parameters(), *self.l2.parameters()):
                p.copy_(0.5 * torch.randn(p.shape, generator=gen, dtype=torch.float64))
        self.requires_grad_(False)

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        d = 1e-3 * self.l2(torch.tanh(self.l1(q)))
        return self._robot[0].fk(q) @ transform(so3_exp(d[..., 3:]), d[..., :3])


def _hybrid_models():
    """(label, cheap model, expensive model) pairs for the Table IV section."""
    f64 = {"dtype": torch.float64}
    rx = hpk.Robot.from_urdf("rx160")
    rx.requires_grad_(False)
    base = transform(
        so3_exp(torch.tensor([0.02, -0.01, 2.0], **f64)), torch.tensor([2.5, 0.8, -0.4], **f64)
    )
    tool = transform(
        so3_exp(torch.tensor([0.1, 0.0, 0.3], **f64)), torch.tensor([0.01, 0.02, 0.15], **f64)
    )
    effects = [
        make_effect(rx, "joint_offset:joint_2", 2e-3),
        make_effect(rx, "link_length:joint_3", [1e-3, -5e-4, 2e-3]),
        make_effect(rx, "joint_compliance:joint_3", 2e-6),
    ]
    calibrated = ExtendedModel(rx, effects, base=base, tool=tool)
    calibrated.requires_grad_(False)
    ur = hpk.Robot.from_urdf("ur10")
    ur.requires_grad_(False)
    return [
        ("rx160 + effects", ExtendedModel(rx, [], base=base, tool=tool), calibrated, rx),
        ("ur10 + MLP residual", ur, SmoothResidual(ur), ur),
    ]


def _table_iv(args) -> None:
    print("\nTable IV shape: errors w.r.t. the expensive model, over all returned solutions")
    header = ("model", "method", "mm mean", "mm std", "deg mean", "deg std", "solved", "ms/tgt")
    print("  {:<20} {:<12} {:>9} {:>9} {:>9} {:>9} {:>7} {:>7}".format(*header))
    for label, cheap, expensive, robot in _hybrid_models():
        q = robot.sample_q(args.hybrid_targets, torch.Generator().manual_seed(7))
        with torch.no_grad():
            T = expensive(q)
        for method, fn in (("two-stage", solve_ik_two_stage), ("Wang et al.", wang_baseline)):
            t0 = time.perf_counter()
            res = fn(cheap, expensive, T, seeds=args.seeds, robot=robot)
            ms = 1e3 * (time.perf_counter() - t0) / args.hybrid_targets
            s = res.error_summary()
            p, o = s["position_mm"], s["orientation_deg"]
            # solved: targets with a solution within 1e-3 mm / 1e-3 deg of the expensive model
            solved = float(res.within_tolerance.any(-1).double().mean())
            print(
                f"  {label:<20} {method:<12} {p['mean']:9.2e} {p['std']:9.2e} {o['mean']:9.2e} "
                f"{o['std']:9.2e} {100 * solved:6.1f}% {ms:7.1f}"
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--robots", nargs="+", default=["ur10", "rx160"])
    ap.add_argument("--targets", type=int, default=200)
    ap.add_argument("--seeds", type=int, default=64)
    ap.add_argument("--iterations", type=int, default=60, help="iteration budget of both")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--tol-mm", type=float, default=1e-3)
    ap.add_argument("--tol-deg", type=float, default=1e-3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-pk", action="store_true")
    ap.add_argument("--no-tracik", action="store_true")
    ap.add_argument("--tracik-timeout", type=float, default=0.005, help="[s] per call")
    ap.add_argument("--no-hybrid", action="store_true", help="skip the Table IV section")
    ap.add_argument("--hybrid-targets", type=int, default=100)
    ap.add_argument(
        "--wrist-near-zero", action="store_true", help="fifth joint within 1e-5..1e-3 rad of 0"
    )
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    solvers = {"hybrid_pk": _ours}
    if not args.no_pk:
        solvers["pytorch-kinematics"] = _pk
    if not args.no_tracik:
        try:
            import trac_ik  # noqa: F401
        except ImportError:
            print("TRAC-IK: pytracik not installed (pip install pytracik), skipped")
        else:
            solvers["TRAC-IK"] = _tracik

    print(
        f"{args.targets} targets, {args.seeds} seeds, {args.iterations} iterations, "
        f"tolerance {args.tol_mm} mm / {args.tol_deg} deg, {args.threads} thread(s)"
    )
    for name in args.robots:
        robot = hpk.Robot.from_urdf(name)
        robot.requires_grad_(False)
        gen = torch.Generator().manual_seed(2024)
        q = robot.sample_q(args.targets, gen)
        if args.wrist_near_zero:
            size = 10 ** (-5 + 2 * torch.rand(args.targets, generator=gen, dtype=q.dtype))
            sign = torch.where(torch.rand(args.targets, generator=gen) < 0.5, -1.0, 1.0)
            q[:, 4] = size * sign.to(q.dtype)
        with torch.no_grad():
            T = robot.fk(q)
        seeds = quasi_random_seeds(robot.lower, robot.upper, robot.revolute, args.seeds)
        reference = eaik_branches(robot, T)
        times: dict[str, list[float]] = {k: [] for k in solvers}
        cpu: dict[str, list[float]] = {k: [] for k in solvers}
        found: dict[str, list] = {}
        for r in range(args.rounds):
            for label, fn in solvers.items():
                if label == "TRAC-IK" and r > 0:
                    continue  # sequential C++ calls: one round is enough
                t0, c0 = time.perf_counter(), time.process_time()
                found[label] = fn(robot, T, seeds, args)
                times[label].append(time.perf_counter() - t0)
                cpu[label].append(time.process_time() - c0)
        print(f"\n{name}: {sum(len(b) for b in reference)} analytic branches within limits")
        ms = {k: 1e3 * statistics.median(v) / args.targets for k, v in times.items()}
        cpu_ms = {k: 1e3 * statistics.median(v) / args.targets for k, v in cpu.items()}
        for label in solvers:
            sols = found[label]
            success = sum(len(s) > 0 for s in sols) / args.targets
            hit, total, _ = branch_coverage(sols, reference)
            print(
                f"  {label:<20} {ms[label]:8.2f} ms/target (CPU {cpu_ms[label]:.2f})  "
                f"success {100 * success:6.2f} %  "
                f"coverage {100 * hit / max(total, 1):6.2f} % ({hit}/{total})  "
                f"{np.mean([len(s) for s in sols]):.2f} solutions/target"
                + (f"  {_WORK[robot.name]:,} evaluations" if label == "hybrid_pk" else "")
            )
        for label in solvers:
            if label != "hybrid_pk":
                wall, used = ms[label] / ms["hybrid_pk"], cpu_ms[label] / cpu_ms["hybrid_pk"]
                print(f"  speed ratio {label} / hybrid_pk: {wall:.1f}x (CPU time {used:.1f}x)")
    if not args.no_hybrid:
        _table_iv(args)


if __name__ == "__main__":
    main()
