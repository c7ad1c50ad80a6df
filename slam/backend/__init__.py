"""Visual-inertial back end: IMU preintegration, initialisation, fixed-lag smoothing."""
