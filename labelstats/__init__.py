"""Label statistics: plain Python over label rows as the export writes them, so a report made
over REST, on a page or from an exported file is the same.

The teacher-calibration report (`calibration`, its Wilson interval, binomial test and noisy
teacher's eps fit in `calibration_stats`), agreement between labellers (`agreement`: pairwise
and Fleiss' kappa) and each labeller's reliability (`labeller_quality`). It reads no table and
opens no transaction: the queue package gives it rows (`labelqueue.export_rows`, or a file
through `rundata.export_read`). It imports only runvocab, and neither torch nor SQLAlchemy.
"""
