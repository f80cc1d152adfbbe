"""Line-oriented serial instruments (a laser interferometer answering ``POS?``, or streaming)."""
