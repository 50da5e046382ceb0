"""Figures drawn from plain data (NumPy and matplotlib's Agg canvas, no torch): learning
curves (`curves`) and the teacher-calibration report (`calibration`). The server and the
experiment reports both import it; it imports only runvocab, the queue package and labelstats."""
