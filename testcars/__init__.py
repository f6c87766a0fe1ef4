"""testcars: test cars that are not the model the calibration fits, and fabricated logs, for tests and
benchmarks.

- :mod:`testcars.synth_perturbed`: a plant whose structure the fitter does not share (its own equations
  and 1 s Euler loop), SYNTHETIC logs with a known truth.
- :mod:`testcars.synth_fastsim`: NREL FASTSim 3's thermal Sonata hybrid as a foreign virtual car
  (optional: the ``fastsim`` extra).
- :mod:`testcars.fabricate`: smooth, bounded streams at realistic per-signal rates for the readers' and
  writers' tests (not a vehicle model).

They use ``calib``'s model, log types and writers; nothing in ``calib`` or ``optimize`` imports them
(``tests/test_architecture.py``). The fitter's own synthesiser, which writes the bundled ``logs/``,
stays in :mod:`calib.synth`.
"""
