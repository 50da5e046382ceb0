"""What the pages read about runs and labels, read-only over the queue's tables: why a run is
waiting and the workers as last seen (`activity`), the label browser (`label_browser`), a
run's flagged pairs (`flags`), and a run's labelling throughput and a labeller's own label
count (`label_stats`). Only the server uses it."""
