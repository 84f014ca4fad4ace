"""Reading and writing oapcal's files: point pairs, calibrations, atomic outputs."""
