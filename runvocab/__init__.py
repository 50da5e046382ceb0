"""The run vocabulary that the trainer, the server and the command line share.

A run's configuration and its presets (`config`), the valid names of tasks, algorithms,
selection rules, teachers and skill backends (`names`, with the task list kept as data in
`tasks.json`), one `validate` for a whole configuration (`validate`), when a run's first
feedback round opens (`first_round`), the configuration a
queued run describes (`queued_run`), and a query's answers (`answers`) and fields
(`query_fields`), which cross from the trainer through the queue into the export, and the one
rule for text a person gives that must say something (`text`). It imports
neither torch nor MuJoCo, so the server checks a run before accepting it with the same messages
`sepoa train` prints.
"""
