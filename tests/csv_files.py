"""The check that a CSV file the package wrote holds the numbers of the arrays it came from."""

from __future__ import annotations

import csv

import numpy as np

from spacegrasp_jax.jobs import runfiles


def assert_csv_holds(path, arrays: dict, rows: int) -> None:
    """``path`` has one column per number of ``arrays`` (name -> array, leading axis the
    rows; ``runfiles.csv_columns`` names them), ``rows`` rows, and every cell equal to its
    array entry: floats bit for bit (an empty cell is NaN), the rest as text."""
    columns = runfiles.csv_columns(arrays)
    with open(path, newline="") as handle:
        read = list(csv.DictReader(handle))
    assert len(read) == rows and list(read[0]) == list(columns)
    for name, values in columns.items():
        cells = [row[name] for row in read]
        if values.dtype.kind in "fc":
            np.testing.assert_array_equal([float(cell) if cell else np.nan for cell in cells], values, err_msg=name)
        else:
            assert cells == [str(value) for value in values.tolist()], name
