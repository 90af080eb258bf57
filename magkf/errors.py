"""The one exception magkf raises for bad input, so the command line can print it on one line."""

from __future__ import annotations

__all__ = ["InputError", "Note", "names_the_log"]


class Note(UserWarning):
    """Something the user should know that is not a suspicion (the command line prints it as ``magkf: note:``)."""


class InputError(ValueError):
    """Bad input data, a malformed file or geometry that cannot determine a fit.

    The one exception magkf raises for bad input, so the command line can print it on one line:
    ``str(error)`` is a single line such as ``log.csv, row 7, column 'mag_x': not a number: 'abc'``.

    Parameters
    ----------
    message : str
        What is wrong.
    source : str or None, optional
        Names the file (or what was passed).
    row : int or None, optional
        The line number in that file, counting the header as row 1.
    column : str or None, optional
        The column name.

    Attributes
    ----------
    message, source, row, column
        As given; each of the last three may be None where it does not apply.
    """

    def __init__(self, message: str, source: str | None = None, row: int | None = None, column: str | None = None):
        self.message, self.source, self.row, self.column = message, source, row, column
        where = [str(source)] if source is not None else []
        if row is not None:
            where.append(f"row {row}")
        if column is not None:
            where.append(f"column {column!r}")
        text = f"{', '.join(where)}: {message}" if where else message
        super().__init__(" ".join(text.split()))

    def located(self, source: str) -> InputError:
        """Return this error, naming ``source`` when it names no file yet.

        Parameters
        ----------
        source : str
            The file to name.

        Returns
        -------
        InputError
            This error itself when it names a file already, else a copy that names ``source``.
        """
        if self.source is not None:
            return self
        return InputError(self.message, source, self.row, self.column)


def names_the_log(function):
    """Decorate a function whose first argument is a ``DriveLog``: an InputError raised inside it that names
    no file (an IGRF date out of range, too few usable epochs) names the log's."""
    import functools

    @functools.wraps(function)
    def wrapper(log, *args, **kwargs):
        try:
            return function(log, *args, **kwargs)
        except InputError as exc:
            raise exc.located(getattr(log, "source", None) or "log") from None

    return wrapper
