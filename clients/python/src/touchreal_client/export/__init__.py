"""Exports of recorded sessions to other tools' formats (:mod:`.nwb`: Neurodata Without Borders)."""
