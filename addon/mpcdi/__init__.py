"""VESA MPCDI: the calibration handed to media servers (the file format, what ProCam writes into it, and how a
media server applies it)."""
