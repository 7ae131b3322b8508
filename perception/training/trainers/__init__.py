"""Training: the loop the three nets share (`loop`), each net's part of it, and what every run
uses (losses, schedule, checkpoints, the weights' manifest, data parallelism)."""
