"""posegrasp's experiment: episodes, the estimator registry, the gymnasium env and the commands.

Importing it has no side effects; rendering is set up by `posegrasp.core.runtime.setup_rendering`,
which the commands and the env call.
"""
