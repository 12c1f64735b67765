"""Judging a sensor under test (radar, camera, lidar object list) against the v2xpos reference:
``v2xpos evaluate`` (``docs/evaluate.md``).

* ``config``      SENSOR.toml: the declared mount, field of view, targets' reported points, CAN map
* ``objects``     the object list: csv, or a CAN log (ASC / BLF / MDF4) decoded with the DBC
* ``reference``   results.csv or a session MCAP: VALID rows, interpolation, the reported point
* ``associate``   the measurement model, gating and gated global nearest neighbour per cycle
* ``effects``     latency, range bias and mounting yaw with sds and significance (``diagnose.identify``)
* ``evaluation``  the steps end to end and the metrics
* ``report``      metrics.json, matches.csv, plots and the HTML page, written all or nothing
"""
