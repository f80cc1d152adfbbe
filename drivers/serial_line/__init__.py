"""Line-oriented serial instruments: the generic ASCII path for a device no plugin speaks for (a query and a
regex on each answer line, or lines the device streams), and an ASCII controller as actuator."""
