"""Offline work behind the learned estimators: data, training, evaluation and shipping.

The modules here are the commands one runs (``python -m perception.training.<command>``):
`datagen` renders the data, `train_posenet`, `train_detector` and `train_masknet` train one net,
`recipe` trains and ships every net behind ``perception/weights/``, `export` ships pose nets one
trained oneself, `tables` scores nets and estimators on the held-out test images and `overlays`
draws the estimator's poses. The packages hold what the commands use, each room one job:

- `data`: rendering, writing and reading the datasets (BOP layout), and the pose nets' crops.
- `evals`: measuring nets on held-out images (pose errors, COCO AP, whole estimators, the
  paper's tables).
- `trainers`: the training loop the three nets share, each net's part of it (data, model, step,
  validation), and what runs share: losses, schedule, checkpoints, data parallelism.
- `shipping`: the recipe's stages, shipping checkpoints into weights with their manifest
  entries, and recording test figures there.
"""
