"""Ground truth: stereo visual odometry, ORB-SLAM output ingestion, pose topics, loop-closure checks."""
