"""What magkf reads and writes.

::

    readers     read_log: every format behind one door (by content and extension)
    drivelog    DriveLog and from_table, the epoch contract; the canonical CSV and Parquet
    ulog        PX4 ULog (pyulog)
    dataflash   ArduPilot DataFlash (pymavlink), the logged calibration undone
    columnmap   any table through a TOML column map
    streams     streams at other rates brought onto the magnetometer's epochs
    timebase    GPS week and milliseconds to UTC
    inspect     what a log holds and allows (magkf check)
    tables      validated numeric tables (file, row and column in every error)
    calibration the calibration value and its versioned JSON file
    autopilot   a calibration as ArduPilot or PX4 parameters
"""
