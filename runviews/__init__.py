"""What the pages read about runs and labels, read-only over the queue's tables: why a run is
waiting and the workers as last seen (`activity`), and the label browser (`label_browser`).
Only the server uses it."""
