"""The ``pi_gcs`` driver kind: a PI piezo controller speaking GCS 2.0 over TCP or a serial port."""
