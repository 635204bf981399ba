"""The accuracy-vs-time sweep (``tools/bench.py``).

Modules:
    sweep   expand a preset into points (stage, knob, value) and run each in its own process
    point   one point: train, evaluate, time inference, report peak memory
    report  ``results.csv``, per-stage tables with ratios and Pareto plots
    main    a composed ``configs/bench.yaml`` -> sweep -> outputs
"""

__all__ = ["main", "point", "report", "sweep"]
