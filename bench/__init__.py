"""Benchmarks, load generators and test tools (``v2xpos bench NAME``; above the services: they may use
master/, slave/ and sim/): fan-in, soak, trust (attacks; fault scenarios on a live loopback rig),
fuzzing, the bad-input corpus, IMU-grading sweeps, the calibration Monte-Carlo, the monitor's cost
against a stand-in master, replay throughput, integrity Monte-Carlo."""
