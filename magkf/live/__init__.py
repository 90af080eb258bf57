"""Calibration of a vehicle while it flies, from its MAVLink stream, and any log replayed as one.

* ``source.MavlinkSource``: the vehicle's link (anything pymavlink's ``mavutil`` connects to): the streams asked
  for, its compass parameters, its messages aligned into samples of the canonical columns, and what went wrong
  on the way (loss, reordering, a rate not the one asked, a reboot, a link that drops);
* ``session.LiveSession``: those samples fed to ``magkf.online.realtime.OnlineCalibrator``, the figures an
  operator watches (``status.LiveStatus``), checkpoints, and the outputs ``calibrate`` writes;
* ``screen``: the status on a terminal, refreshed in place, or as JSON lines;
* ``replay``: a log sent as a vehicle's MAVLink messages, answering parameter requests.
"""
