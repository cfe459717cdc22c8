"""pi0-jax: π0 / π0.5 vision-language-action models in JAX/Flax."""

from pi0_jax.config import IMAGE_KEYS, PRESETS, Pi0Config, get_config

__all__ = ["IMAGE_KEYS", "PRESETS", "Pi0Config", "get_config"]
__version__ = "0.1.0"
