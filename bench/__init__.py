"""Benchmarks, load generators and test tools (above the services: they may use master/, slave/ and sim/)."""
