"""The compliance's feedback ``(I + C dg/dq)^-1`` in the structured Jacobian is solved on
the 6 twist rows, ``(P M^-1) dq``, not on every candidate column, ``P (M^-1 dq)``: the
same product, equal to the column-by-column solve at float64 round-off."""

from __future__ import annotations

import torch

from hybrid_pk.calibration.loaded_jacobian import loaded_state
from hybrid_pk.calibration.problem import param_blocks
from hybrid_pk.calibration.structured_jacobian import StructuredJacobian
from hybrid_pk.calibration.twists import point_joint_twists
from hybrid_pk.effects import ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.simulate import simulate_campaign

F64 = torch.float64


def _compliant_model(ur10) -> ExtendedModel:
    """Two compliances at UR10-like values [rad/Nm] and a joint effect of each kind."""
    effects = [
        make_effect(ur10, "joint_compliance:shoulder_lift_joint", 8e-6),
        make_effect(ur10, "joint_compliance:elbow_joint", 5e-6),
        make_effect(ur10, "joint_offset:wrist_1_joint", 3e-4),
        make_effect(ur10, "gear_ratio:elbow_joint", 2e-4),
        make_effect(ur10, "backlash:shoulder_pan_joint", 1e-4),
        make_effect(ur10, "joint_eccentricity:wrist_2_joint", torch.tensor([2e-4, -1e-4])),
    ]
    model = ExtendedModel(ur10, effects)
    with torch.no_grad():  # frames away from the identity: the rows' rotation matters
        model.base.rotvec.copy_(torch.tensor([[0.1, -0.2, 0.3]], dtype=F64))
        model.tool.dp.copy_(torch.tensor([[0.01, 0.02, 0.1]], dtype=F64))
    return model


def test_feedback_on_the_twist_rows_equals_it_on_every_column(ur10):
    data, _ = simulate_campaign(ur10, 200, "none", noise_mm=0.02, payload=5.0, seed=4)
    model = _compliant_model(ur10)
    cond = conditions_from_data(data)
    blocks = [b for b in param_blocks(model, None, False) if b.name.startswith("effects.")]
    sj = StructuredJacobian(model, blocks)
    twists = sj.pose_twists(data.q, cond).twists
    # the column-by-column path, as it was: dq* = M^-1 dq on every column, then P dq*
    with torch.no_grad():
        params, gravity, q_star, _, bent, _ = loaded_state(model, data.q, cond)
        dq, feedback = sj._joint_derivatives(data.q, cond, q_star, params, None, gravity)
        E = ur10.fk(q_star, params=bent)
        lever = (E @ model.tool.matrix()[0])[:, :3, 3] - E[:, :3, 3]
        R_B = model.base.matrix()[0][:3, :3]
        P = point_joint_twists(ur10.jacobian(q_star, params=bent), lever, R_B)
    assert feedback is not None
    assert float((feedback - torch.eye(6, dtype=F64)).abs().max()) > 1e-4
    old = P @ torch.linalg.solve(feedback, dq)
    assert twists.shape == old.shape == (200, 6, 7)
    scale = old.abs().amax(dim=(0, 1))  # per column: units differ between blocks
    assert bool((scale > 0).all())
    assert float(((twists - old).abs().amax(dim=(0, 1)) / scale).max()) < 1e-12


def test_a_soft_joint_settles_to_the_stated_tolerance(rx160):
    """The compliance fixed point without derivatives stops at its tolerance
    (``COMPLIANCE_TOL_RAD``), also on a soft joint where four steps are not enough: an
    RX160 shoulder at 2.3e-5 rad/Nm (contraction ~0.01 from a ~0.01 rad sag) left
    1e-10 rad with four. Checked against the fixed point iterated far past it."""
    from hybrid_pk.effects.extended import COMPLIANCE_TOL_RAD

    model = ExtendedModel(rx160, [make_effect(rx160, "joint_compliance:joint_2", 2.3e-5)])
    q = rx160.sample_q(200, torch.Generator().manual_seed(3))
    data, _ = simulate_campaign(rx160, 200, "none", poses=q, noise_mm=0.0, payload=20.0, seed=1)
    cond = conditions_from_data(data)
    with torch.no_grad():
        settled = model.joint_values(q.clone(), cond)  # fresh rows: a cold start
        g = model.gravity_root(cond)
        c = torch.zeros(rx160.dof, dtype=F64)
        c[1] = 2.3e-5  # joint_2's compliance, written out: the oracle's own
        payload = 0.0 if cond.payload is None else cond.payload
        ref = q.clone()
        for _ in range(60):  # contraction ~0.01: far below round-off
            ref = q - c * rx160.gravity_torques(ref, payload=payload, gravity=g)
    sag = float((ref - q).abs().max())
    assert sag > 1e-3  # the joint is soft: four steps would leave ~sag^5
    assert float((settled - ref).abs().max()) <= 10 * COMPLIANCE_TOL_RAD
