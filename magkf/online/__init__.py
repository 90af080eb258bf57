"""The online calibration of ``R`` and ``b`` (and added effects) over a log, or in a real-time loop.

The pipeline, module by module::

    prepare       per-log work once: reference field, attitude, body-frame field, statuses; the start
    bootstrap     a start from the log itself when no offline calibration is given
    state         StateLayout: the core block, each effect's block, the calibrated field
    measurements  measurement models (magnitude, vector, both): linearisation, sigma points, batch residuals
    filters       EKF and UKF behind one interface (predict, linearise, update, inflate, copy)
    estimator     gates and updates for a block of epochs, shared by logs and real time
    run           calibrate_log: blocks of a log through the estimator, then results
    smoother      Rauch-Tung-Striebel pass over the filter's steps
    batch         solve_batch: the whole log by robust least squares
    realtime      OnlineCalibrator: a sample (or a burst) at a time, constant memory
    results       CalibrationRun and RunSummary
    observability which directions the data did not determine

Users call ``magkf.calibrate_log``, ``magkf.solve_batch`` and ``magkf.OnlineCalibrator``.
"""
