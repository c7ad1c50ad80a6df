"""The online SLAM system: messages, config, calibration, geometry, stages and estimators."""
