"""Training π0 with the flow-matching loss (spec §7) on the MJX suite's expert demonstrations.

  config.py   TrainConfig and its named presets (pi0_small_suite: the demo model; dummy_smoke: CPU tests)
  data.py     demos directory -> host arrays; norm stats; the suite's SentencePiece tokenizer
  augment.py  spec §5.1 training augmentation (crop / resize / rotate, colour jitter) in JAX
  step.py     the jitted, data-parallel train step: batch on device, loss, AdamW, EMA
  trainer.py  the loop: logging, train-state checkpoints, exact resume, export of a pi0-jax checkpoint
  distill.py  flow-step distillation of a trained checkpoint into a 1-2 step (optionally shallower) student
  cli.py      `pi0-jax train`, `pi0-jax distill`

The full pipeline for the demo model (one GPU; scripts/gpu_suite.sh runs it):

  python scripts/sim_demos.py DEMOS --suite all --episodes-per-task 400 --first-init 50 --resolution 112 \\
      --no-compress --batch 550 --action-noise 0.2        # DART demos on initial states 50..449 (eval: 0..49)
  pi0-jax train --config pi0_small_suite --demos DEMOS --out RUN
  pi0-jax eval --policy RUN/checkpoint --resolution 112 --episodes-per-task 50
"""
