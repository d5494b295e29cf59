"""Measured data: the pose table of contract section 1 and importers of other formats."""

from hybrid_pk.data.measured import MeasuredData as MeasuredData
from hybrid_pk.data.measured import SkippedRow as SkippedRow
from hybrid_pk.data.table import DataWarning as DataWarning
from hybrid_pk.data.table import IgnoredColumnsWarning as IgnoredColumnsWarning
from hybrid_pk.data.table import SkippedRowsWarning as SkippedRowsWarning
from hybrid_pk.data.table import read_table as read_table
from hybrid_pk.data.table import read_table_for as read_table_for
from hybrid_pk.data.table import write_table as write_table

__all__ = [
    "DataWarning",
    "IgnoredColumnsWarning",
    "MeasuredData",
    "SkippedRow",
    "SkippedRowsWarning",
    "read_table",
    "read_table_for",
    "write_table",
]
