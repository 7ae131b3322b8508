"""What one episode is made of: the estimators' registry (`sim.episodes.registry`) and the
oracle's pose noise (`sim.episodes.pose_noise`)."""
