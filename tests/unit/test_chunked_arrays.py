"""``igrf_ned`` interpolates and ``euler_to_dcm`` makes its matrices a chunk of epochs at a time: bit for bit the
arrays made in one piece."""

import numpy as np

from magkf import conventions, reference
from magkf.conventions import ATTITUDE


def test_igrf_in_chunks_is_igrf_in_one_piece(monkeypatch):
    """A path over several knots and an IGRF epoch (2025-01-01), with missing positions (counted out before the
    chunks are cut); one epoch alone and a grid of epochs keep their shapes."""
    rng = np.random.default_rng(7)
    n = 3000
    t = 1735689600.0 - 1500.0 + np.arange(n) * 1.0  # across 2025-01-01
    lat = 48.1 + np.cumsum(rng.normal(0, 2e-4, n))
    lon = 11.6 + np.cumsum(rng.normal(0, 2e-4, n))
    alt = 500.0 + np.cumsum(rng.normal(0, 1.0, n))
    lat[[5, 996, 997, 2999]] = np.nan
    whole = reference.igrf_ned(t, lat, lon, alt)
    monkeypatch.setattr(reference, "INTERPOLATION_CHUNK", 997)
    chunked = reference.igrf_ned(t, lat, lon, alt)
    assert np.isnan(chunked[[5, 996, 997, 2999]]).all()
    np.testing.assert_array_equal(chunked, whole)
    np.testing.assert_array_equal(
        reference.igrf_ned(t, lat, lon, 500.0), reference.igrf_ned(t, lat, lon, np.full(n, 500.0))
    )
    # one epoch (0-d: its own knot, ppigrf's value there) and a grid of epochs (the same path, in the grid's shape)
    one = reference.igrf_ned(t[100], lat[100], lon[100], alt[100])
    assert one.shape == (3,)
    np.testing.assert_allclose(
        one, reference.ppigrf_ned(t[100:101], lat[100:101], lon[100:101], alt[100:101])[0], rtol=1e-12
    )
    grid = reference.igrf_ned(*(v.reshape(60, 50) for v in (t, lat, lon, alt)))
    assert grid.shape == (60, 50, 3)
    np.testing.assert_array_equal(grid.reshape(-1, 3), chunked)


def test_the_track_made_for_the_epochs_read_is_the_whole_field(monkeypatch):
    """``IgrfTrack[rows]`` (positions with and without a position among them, a slice, none) is ``igrf_ned``'s rows
    bit for bit, read in chunks of 997 across a date and many knots."""
    rng = np.random.default_rng(10)
    n = 3000
    t = 1735689600.0 - 1500.0 + np.arange(n) * 1.0
    lat = 48.1 + np.cumsum(rng.normal(0, 2e-4, n))
    lon = 11.6 + np.cumsum(rng.normal(0, 2e-4, n))
    alt = 500.0 + np.cumsum(rng.normal(0, 1.0, n))
    lat[[0, 5, 996, 997, 2999]] = np.nan
    whole = reference.igrf_ned(t, lat, lon, alt)
    monkeypatch.setattr(reference, "INTERPOLATION_CHUNK", 997)
    track = reference.IgrfTrack(t, lat, lon, alt)
    rows = np.sort(rng.choice(n, 1200, replace=False))
    rows = np.union1d(rows, [0, 5, 996, 2999])
    np.testing.assert_array_equal(track[rows], whole[rows])
    np.testing.assert_array_equal(track[1000:2500], whole[1000:2500])
    np.testing.assert_array_equal(track[:], whole)
    assert track[np.zeros(0, int)].shape == (0, 3)
    assert len(track) == n and track.shape == (n, 3)
    nowhere = reference.IgrfTrack(t, np.full(n, np.nan), lon, alt)
    assert np.isnan(nowhere[rows]).all()


def test_knots_summed_in_chunks_start_where_the_whole_path_says(monkeypatch):
    """The knots' first epochs, the path summed a chunk at a time (chunks of 997 and 1, across the date line), are
    where the path summed over the whole track in one ``cumsum`` passes each whole spacing."""
    rng = np.random.default_rng(9)
    n = 3000
    lat = 48.1 + np.cumsum(rng.normal(0, 2e-4, n))
    lon = (179.9 + np.cumsum(rng.normal(0, 2e-4, n)) + 180.0) % 360.0 - 180.0
    alt = 500.0 + np.cumsum(rng.normal(0, 1.0, n))
    dn = np.radians(np.diff(lat)) * reference.EARTH_RADIUS_M
    de = np.radians((np.diff(lon) + 180.0) % 360.0 - 180.0) * reference.EARTH_RADIUS_M * np.cos(np.radians(lat[1:]))
    path = np.concatenate([[0.0], np.cumsum(np.sqrt(dn**2 + de**2 + np.diff(alt) ** 2))])
    knot = np.floor(path / 500.0).astype(np.int64)
    expected = np.flatnonzero(np.diff(knot, prepend=-1))
    assert 50 < len(expected) < n  # many knots, several epochs to one
    for chunk in (997, 1):
        monkeypatch.setattr(reference, "INTERPOLATION_CHUNK", chunk)
        np.testing.assert_array_equal(reference._knot_starts(lat, lon, alt, 500.0), expected)
    np.testing.assert_array_equal(reference._knot_starts(lat[:1], lon[:1], alt[:1], 500.0), [0])


def test_dcm_in_chunks_is_dcm_in_one_piece(monkeypatch):
    """Attitude of many epochs, and a scalar pitch broadcast: the same matrices in chunks of 7."""
    rng = np.random.default_rng(8)
    yaw, pitch, roll = rng.uniform(-180, 180, 100), rng.uniform(-90, 90, 100), rng.uniform(-180, 180, 100)
    whole = conventions.euler_to_dcm(yaw, pitch, roll)
    broadcast = conventions.euler_to_dcm(yaw, 12.5, roll)
    monkeypatch.setattr(conventions, "DCM_CHUNK", 7)
    np.testing.assert_array_equal(conventions.euler_to_dcm(yaw, pitch, roll), whole)
    np.testing.assert_array_equal(conventions.euler_to_dcm(yaw, 12.5, roll), broadcast)


def test_attitude_matrices_made_when_read_are_the_held_ones():
    """``AttitudeMatrices`` gives, for a slice, a mask, an index array, one position and the whole stack, bit for bit
    the matrices ``euler_to_dcm`` makes of all epochs at once (NaN rows where the attitude is missing); an array's
    attribute, arithmetic and a NumPy function take the whole stack."""
    rng = np.random.default_rng(9)
    n = 200_000  # several of euler_to_dcm's chunks
    attitude = np.column_stack([rng.uniform(-180, 180, n), rng.uniform(-90, 90, n), rng.uniform(0, 360, n)])
    attitude[[3, 70_000, n - 1]] = np.nan
    held = conventions.euler_to_dcm(attitude[:, 2], attitude[:, 1], attitude[:, 0])
    lazy = conventions.AttitudeMatrices(attitude)
    assert len(lazy) == n and lazy.shape == held.shape
    mask = rng.random(n) < 0.3
    index = np.flatnonzero(mask)[::-1]
    for key in (slice(None), slice(65_530, 131_080), mask, index, 70_000, 5):
        np.testing.assert_array_equal(lazy[key], held[key])
    np.testing.assert_array_equal(np.asarray(lazy), held)
    np.testing.assert_array_equal(lazy.T, held.T)
    np.testing.assert_array_equal(2.0 * lazy, 2.0 * held)
    np.testing.assert_array_equal(np.swapaxes(lazy, -1, -2), np.swapaxes(held, -1, -2))
    np.testing.assert_array_equal(lazy[:, 2, 0], held[:, 2, 0])


def test_a_column_stack_reads_as_the_stacked_columns():
    """``ColumnStack`` gives, for a slice, a mask, an index array, one position, an index into both axes and the
    whole stack, the rows of the columns stacked side by side, holding the columns themselves; ``AttitudeMatrices``
    of it gives the matrices of the stacked angles bit for bit."""
    rng = np.random.default_rng(10)
    n = 1_000
    columns = [rng.uniform(-180, 180, n), rng.uniform(-90, 90, n), rng.uniform(0, 360, n)]
    columns[1][[4, 500]] = np.nan
    stacked = np.column_stack(columns)
    lazy = conventions.ColumnStack(*columns)
    assert len(lazy) == n and lazy.shape == (n, 3)
    assert all(a is b for a, b in zip(lazy.columns, columns))  # held, not copied
    mask = rng.random(n) < 0.3
    for key in (slice(None), slice(7, 700, 3), mask, np.flatnonzero(mask)[::-1], 500, -1, (slice(2, 9), 1)):
        np.testing.assert_array_equal(lazy[key], stacked[key])
    np.testing.assert_array_equal(np.asarray(lazy), stacked)
    np.testing.assert_array_equal(
        np.asarray(conventions.AttitudeMatrices(lazy)), np.asarray(conventions.AttitudeMatrices(stacked))
    )


def test_a_prepared_log_holds_its_attitude_not_its_matrices():
    """``prepare`` holds the attitude matrices as ``AttitudeMatrices`` (the angles), whose rows are those the
    whole-stack ``body_arrays`` makes, and so are the body field and the heading axis made a chunk at a time;
    without ``rates`` no rates; pieces joined (``concat_prepared``) stay made when read. The angles are the log's own
    columns (``ColumnStack``), not a copy. Traced, preparing 200 000 epochs without the rates holds less than the
    arrays it keeps (114 bytes an epoch: the reading, the field in two frames and its magnitude, the heading axis,
    the DOP and the statuses) and 40 bytes an epoch of working arrays and one chunk; a copy of the angles (24 bytes
    an epoch) and the matrices held (72) would not fit."""
    import tracemalloc

    from magkf.config import FilterConfig
    from magkf.io.drivelog import DriveLog
    from magkf.online import prepare as prep_module
    from magkf.sim.drive import DriveConfig, simulate_drive

    table = simulate_drive(DriveConfig(duration_s=4000.0, rate_hz=50.0, seed=3)).table
    kept = ("mag_x", "mag_y", "mag_z", "roll", "pitch", "yaw", "lat", "lon", "alt", "dop")
    log = DriveLog(table[[c for c in table if c in kept]], "sim.csv")  # no auxiliary channels
    config = FilterConfig()
    prep = prep_module.prepare(log, config)
    assert isinstance(prep.c_nb, conventions.AttitudeMatrices)
    assert isinstance(prep.c_nb.attitude, conventions.ColumnStack)
    assert all(np.shares_memory(c, log.table[name].to_numpy()) for c, name in zip(prep.c_nb.attitude.columns, ATTITUDE))
    c_nb, field_body, heading = prep_module.body_arrays(log.attitude, prep.ref)
    np.testing.assert_array_equal(np.asarray(prep.c_nb), c_nb)
    np.testing.assert_array_equal(prep.data.field_body, field_body)
    np.testing.assert_array_equal(prep.heading, heading)
    lean = prep_module.prepare(log, config, rates=False)
    assert lean.data.field_body_rate is None and lean.data.field_body_accel is None
    np.testing.assert_array_equal(lean.data.field_body, prep.data.field_body)
    joined = prep_module.concat_prepared([prep.take(slice(0, 1000)), prep.take(slice(1000, None))])
    assert isinstance(joined.c_nb, conventions.AttitudeMatrices)
    assert isinstance(joined.data.c_nb, conventions.AttitudeMatrices)
    np.testing.assert_array_equal(np.asarray(joined.c_nb), c_nb)
    assert prep.take(5).c_nb.shape == (3, 3)  # one epoch's matrix, made
    # a block's matrices are made once where the model reads its data (a plug-in model may read them per sigma
    # point) or the effects do; the core alone does not read them
    from magkf.online.estimator import run_model
    from magkf.online.state import StateLayout

    layout = StateLayout.with_core()
    x0 = layout.prior()[0]
    x0[:9] = np.eye(3).ravel()
    model = run_model(config, layout, x0)
    block = prep.block(slice(100, 150), layout, model, np.eye(3), with_data=True)
    assert type(block.data.c_nb) is np.ndarray
    np.testing.assert_array_equal(block.data.c_nb, c_nb[100:150])
    assert isinstance(prep.data.take(slice(100, 150), lazy=True).c_nb, conventions.AttitudeMatrices)
    assert type(prep.data.take(slice(100, 150)).c_nb) is np.ndarray
    del prep, joined, c_nb, field_body, heading, lean

    n = len(log.table)
    tracemalloc.start()
    try:
        held = prep_module.prepare(log, config, rates=False)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(held) == n
    chunk = prep_module.CHUNK * 3 * 3 * 8 * 4  # a chunk's matrices and their products
    assert peak < (114 + 40) * n + chunk, peak / n


def test_vector_least_squares_in_chunks_is_the_one_piece_fit(monkeypatch):
    """The bootstrap's robust least squares made of regressors a chunk at a time (7 epochs) gives the fit of
    regressors made at once, with an added linear effect's regressors and a prior, to rounding; and the fit finds
    the calibration of noise-free readings with a few gross outliers down-weighted."""
    from magkf.online import bootstrap

    rng = np.random.default_rng(12)
    n = 500
    B = rng.normal(size=(n, 3)) * 30_000.0
    R = np.eye(3) + rng.normal(0, 0.02, (3, 3))
    b = np.array([300.0, -200.0, 500.0])
    extra = rng.normal(size=(n, 3, 2))
    theta = np.array([40.0, -25.0])
    m = B @ R.T + b + extra @ theta + rng.normal(0, 20.0, (n, 3))
    m[[10, 250, 499]] += 5_000.0
    prior = (np.concatenate([np.eye(3).ravel(), np.zeros(5)]), np.concatenate([np.full(9, 0.1), np.full(5, 5e3)]))
    whole = bootstrap.vector_least_squares(m, B, 20.0, *prior, extra=extra)
    monkeypatch.setattr(bootstrap, "FIT_CHUNK", 7)
    chunked = bootstrap.vector_least_squares(m, B, 20.0, *prior, extra=extra)
    for got, want in zip(chunked, whole):
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12 * np.abs(want).max())
    x, cov, w = chunked
    truth = np.concatenate([R.ravel(), b, theta])
    assert np.all(np.abs(x - truth) < 5 * np.sqrt(np.diag(cov)))
    assert w[[10, 250, 499]].max() < 0.1
