"""The demo's table of injected against found effects, without training (issue 28):
``python bench/demo_unseen.py 3000 1,2,3`` (rows, demo seeds): simulate as the demo
does, diagnose the calibration rows, mark what the frames absorb, print the table."""

import sys
import time

from hybrid_pk.calibration.diagnosis import diagnose
from hybrid_pk.calibration.diagnosis.unseen import mark_unseen
from hybrid_pk.calibration.settings import DiagnosisSettings
from hybrid_pk.pipelines.demo import _Split, hidden_effects
from hybrid_pk.pipelines.demo_report import found_table
from hybrid_pk.robot import Robot
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.simulate.effect_specs import effect_entry

r = Robot.from_urdf("rx160")
r.requires_grad_(False)
n = int(sys.argv[1])
for seed in [int(s) for s in sys.argv[2].split(",")]:
    t = time.time()
    voc, un = hidden_effects(r, "random:3", seed=seed, payload=20.0)
    data, truth = simulate_campaign(
        r, n, voc + un, noise_mm=0.02, noise_deg=0.002, payload=20.0, seed=seed
    )
    truth["effects"] = [effect_entry(e) for e in voc]
    truth["unmodelled"] = [{**effect_entry(e), "tau0_Nm": e.tau0} for e in un]
    split = _Split(data)
    diag = diagnose(r, split.calib, **DiagnosisSettings(seed=seed).keywords())  # the demo's
    truth["effects"] = mark_unseen(diag.nominal_model, split.calib, split.cond, truth["effects"])
    print(f"seed {seed} ({time.time() - t:.0f} s)", flush=True)
    for row in found_table(truth, diag):
        print("   ", row, flush=True)
