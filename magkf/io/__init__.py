"""What magkf reads and writes.

::

    readers        read_log: every format behind one door (by content and extension)
    drivelog       DriveLog and from_table, the epoch contract; the canonical CSV and Parquet
    site           --site and --date: a fixed place and start time for a log without GNSS
    ulog           PX4 ULog of every generation (pyulog)
    ulog_combined  the magnetometer of sensor_combined in ULogs of PX4 v1.4 to v1.7
    px4_sensors    how PX4 v1.4 to v1.7 calibrated that magnetometer, and the way back
    ulog_write     a drive-log table written as a ULog of a chosen PX4 generation
    dataflash      ArduPilot DataFlash 3.x to 4.x (pymavlink), the logged calibration undone
    tlog           MAVLink telemetry logs (.tlog), read and written
    rosbag         ROS 1 and ROS 2 bags (SQLite, MCAP; rosbags), ENU/FLU turned into NED/FRD
    columnmap      any table through a TOML column map
    matfile        a numeric array of a MATLAB .mat file as a table
    sniff          the layout of a text table that is not magkf's CSV, to name the map that reads it
    streams        streams at other rates brought onto the magnetometer's epochs
    timebase       GPS week and milliseconds to UTC
    tables         validated numeric tables (file, row and column in every error)
    autopilot      a calibration as ArduPilot or PX4 parameters

The log inspection behind ``magkf check`` is ``magkf.diagnostics.inspect``; the calibration file is
``magkf.calibration``.
"""
