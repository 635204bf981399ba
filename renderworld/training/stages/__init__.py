"""Training stages of the RenderWorld pipeline (registered on import of their module).

Each module is named by its stage config's ``_target_module_`` and imported only when that
stage runs: ``tokenizer`` (AM-VAE / VQ-VAE), ``world_model`` and ``img2occ``.
"""

__all__: list[str] = []
