"""A run's data files, on the queue's tables: the episode store its queries point into
(`episodes`), its data and labels as a Minari dataset (`dataset`, `dataset_env`), label export
files and reading them back (`label_files`, `export_read`), and labelling-only runs over a
dataset (`labelling`)."""
