"""Odometry + sonar fusion: wheel dead reckoning with covariance, an EKF for the map pose fed by the
localiser's corrections, sonar scans in base_link and a sonar fitness term for the fly evolver."""
