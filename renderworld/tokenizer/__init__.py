"""Scene tokenizers: AM-VAE (air / non-air codebooks) and a plain VQ-VAE baseline."""

from renderworld.tokenizer.tokens import Tokens

__all__ = ["Tokens"]
