"""Camera-IMU calibration checks from a recording (`slam calib check`)."""
