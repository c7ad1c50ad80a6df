"""The visual front end: features, KLT tracking, stereo matching, PnP and keyframe decisions."""
