"""Measured data: the pose table (contract section 1) and importers of other formats.

- :mod:`~hybrid_pk.data.measured`: :class:`MeasuredData`, the rows of one campaign.
- :mod:`~hybrid_pk.data.table`: read and validate tables (CSV / Parquet), write them;
  cell and row checks in :mod:`~hybrid_pk.data.cells`, files in
  :mod:`~hybrid_pk.data.files`; joint-only tables (planned poses, robot programs) in
  :mod:`~hybrid_pk.data.joint_table`.
- importers: :mod:`~hybrid_pk.data.mapping` (any export through a column map),
  :mod:`~hybrid_pk.data.ipa` (the published UR10 laser-tracker data),
  :mod:`~hybrid_pk.data.streams` (a robot joint stream and a tracker stream on two
  clocks; the offset in :mod:`~hybrid_pk.data.time_offset`, clock jumps inside the
  streams in :mod:`~hybrid_pk.data.clock_jump`).
"""

from hybrid_pk.data import table
from hybrid_pk.data.measured import MeasuredData as MeasuredData
from hybrid_pk.data.measured import SkippedRow as SkippedRow
from hybrid_pk.data.table import DataWarning as DataWarning
from hybrid_pk.data.table import IgnoredColumnsWarning as IgnoredColumnsWarning
from hybrid_pk.data.table import RepeatedRowsWarning as RepeatedRowsWarning
from hybrid_pk.data.table import SkippedRowsWarning as SkippedRowsWarning
from hybrid_pk.data.table import read_table as read_table
from hybrid_pk.data.table import read_table_for as read_table_for
from hybrid_pk.data.table import to_frame as to_frame
from hybrid_pk.data.table import write_frame as write_frame
from hybrid_pk.data.table import write_table as write_table

__all__ = ["MeasuredData", "SkippedRow", *table.__all__]
