"""Benchmarks (commands, not tests: they print medians and assert no time), behind
`python -m ggns bench {sim,models,tradeoff}`:

    timing.py    the shared timers: device sync, medians, the timed simulator trajectories and
                 the timed rollouts of a learned simulator
    report.py    the one table printer
    sim.py       the ground-truth simulator and the depth sensor (`bench_sim`)
    models.py    training and rollout throughput of the learned simulators against the reference
                 figures and goals of conf/bench/models.yaml (`bench_models`)
    tradeoff.py  the speed/accuracy trade: simulator at coarser time steps against learned
                 simulators (`tradeoff`)
    online.py    the online simulator's time per tick, without and with an observation (`bench online`)
    online_study.py  tracking error of the online simulator fed (late, flawed) depth frames against the
                 blind baselines (`bench online-study`)

`python -m ggns bench learning` (learning per CPU-second) is an experiment that runs fits:
ggns.sweeps.learning.
"""
