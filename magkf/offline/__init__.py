"""The offline calibrations, scikit-learn style estimators (``base``): ``sinefit`` (a two-plane turntable
run, nine parameters) and ``ellipsoid`` (ellipsoid or ellipse fit of any vector sensor)."""
