"""The main job (``tools/run_pipeline.py``, ``make demo``): its steps, up-to-date checks and report.

Modules:
    runner    a small resumable runner: steps are commands with fingerprinted inputs
    main_job  the steps of the main job and the report gathered from their outputs
    report    markdown tables, training curves and the report file
"""

__all__ = ["main_job", "report", "runner"]
