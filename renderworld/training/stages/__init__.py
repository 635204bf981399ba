"""Training stages of the RenderWorld pipeline (registered on import of their module).

Each stage's module or package is named by its stage config's ``_target_module_`` and imported
only when that stage runs: ``tokenizer`` (AM-VAE / VQ-VAE, a module), ``world_model`` and
``img2occ`` (packages: the stage class in their ``stage`` module, its parts beside it).
"""

__all__: list[str] = []
