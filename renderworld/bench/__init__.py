"""The accuracy-vs-time sweep (``tools/bench.py``).

Modules:
    knobs            what each stage can change and what it measures
    sweep            expand a preset into points (stage, knob, value, seed)
    run              run each point in its own process (reusing measured ones), ``jobs`` at once
    point            one training point: train, evaluate, time inference, report peak memory
    planner_point    one planner point: the main job's planner with one option changed, timed
    planner_latency  the planner latency machinery (shared with benchmarks/bench_planner.py)
    estimate         the preset's time estimate printed at start
    report           ``results.csv``, per-stage tables (seed mean and spread, ranking check)
    plots            Pareto plots per stage, the planner's latency chart
    main             a composed ``configs/bench.yaml`` -> sweep -> tables and plots
"""

__all__ = ["estimate", "knobs", "main", "planner_latency", "planner_point", "plots", "point",
           "report", "run", "sweep"]  # fmt: skip
