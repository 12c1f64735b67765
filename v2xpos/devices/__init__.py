"""Live devices: byte streams from receivers and IMUs, stamped on arrival, framed and decoded.

Module map (floor: formats/devices -- uses foundations, ``datasets`` and ``types`` only):

* ``transport``: serial port (pyserial) and TCP client, each on a reader thread that stamps every
  chunk with the host's GPS time (as an RTKLIB TIMETAG file does); optional recording with a
  TIMETAG file.
* ``framing``: incremental, checked framing of UBX / NMEA / RTCM3 frames and of text lines.
* ``ubx`` (pyubx2), ``nmea`` (pynmeagps), ``imu_lines`` (the recorded csv format): frames ->
  records (``records``: GnssEpoch, HeadingObs, ImuRecord, ReceiverTime).
* ``clock_model``: the online lower-envelope counter -> GPS time model of an IMU.
* ``stream``: one device = transport + framer + decoders, built from a config table.
* ``rtcm``: RTCM3 frame checks (pyrtcm), an NTRIP v1/v2 client and a base-station stream reader.
* ``emulate``: ``v2xpos emulate``: a recording's bytes into pseudo-terminals or TCP at their
  recorded arrival times.

The ``device`` source (``v2xpos.sources.device``) runs these streams through the INS filter.
"""
