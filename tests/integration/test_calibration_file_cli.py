"""``magkf apply`` on a malformed calibration file: exit status 2 and one line naming the file (run as a command;
the reader's own refusals are in ``tests/unit/test_calibration_file.py``)."""

import pytest

from magkf.calibration import Calibration
from magkf.errors import InputError

from ..conftest import DATA, run_cli


@pytest.mark.parametrize(
    "content,message",
    [
        ("{not json", "not valid JSON"),
        ("[1, 2]", "one JSON object"),
        ('{"b": [0, 0, 0]}', "required key 'R'"),
        ('{"R": [[1, 0, 0], [0, 1, 0]], "b": [0, 0, 0]}', "shape"),
        ('{"R": [[1, 0, 0], [0, 1, 0], [0, 0, "x"]], "b": [0, 0, 0]}', "must hold numbers"),
        ('{"R": [[1, 0, 0], [0, 1, 0], [0, 0, 0]], "b": [0, 0, 0]}', "singular"),
        ('{"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "b": [0, 0, 0], "version": 99}', "version"),
        ('{"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "b": [0, 0, 0], "format": "other"}', "format"),
    ],
)
def test_malformed_files_are_rejected(tmp, content, message):
    path = tmp / "bad.json"
    path.write_text(content)
    with pytest.raises(InputError, match=message) as err:
        Calibration.load(path)
    assert str(path) in str(err.value)
    proc = run_cli("apply", DATA / "example_drive.csv", "--cal", path)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and str(path) in proc.stderr and message.split("'")[0] in proc.stderr
