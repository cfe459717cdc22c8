"""Peer implementations timed beside pi0-jax by `pi0-jax benchmark --compare ...`. These may import torch;
`pi0_jax` never imports them except on request."""
