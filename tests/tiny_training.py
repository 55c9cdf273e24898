"""The smallest training configuration that runs the whole pipeline (shared by the training tests).

``--set`` overrides for :func:`training.config.load_config`: the stand-in dataset of
``test_training_standin.py`` (this folder must be on ``sys.path``), a 1-block CNN 8 wide, 6 steps,
a 2-bin final evaluation.
"""

TINY = [
    "data.dataset=test_training_standin:StandinDataset",
    "data.height=64", "data.width=64", "data.batch_size=4", "data.val_size=8", "data.num_workers=0",
    "model.tile=32", "model.stride=16", "model.hidden=8", "model.blocks=1",
    "optim.steps=6", "optim.warmup_steps=2", "optim.normaliser_batches=1",
    "log_every=2", "val_every=3", "ckpt_every=2", "threads=1",
    "eval.bins=2", "eval.samples=4", "eval.textureless_samples=2", "eval.height=64", "eval.width=64",
    "eval.options={}", 'eval.textureless_options={"textureless_fraction": 1.0}',
]
