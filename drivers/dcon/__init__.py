"""DCON ASCII thermocouple modules (ADAM-4018/4118, ICP DAS I-7018) on RS-485 or a TCP gateway."""
