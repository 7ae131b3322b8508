"""What one episode is made of: the episode itself, from seed to score (`sim.episodes.episode`),
the estimators' registry (`sim.episodes.registry`) and the oracle's pose noise
(`sim.episodes.pose_noise`)."""
