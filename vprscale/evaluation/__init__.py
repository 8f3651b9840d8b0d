"""Evaluation and reports: the protocol, the grid, the accounting, the report, SQL over an index (docs/protocol.md)."""
