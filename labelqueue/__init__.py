"""The queue database: the only contract between the trainer's workers and the server.

Tables are in `models`; the operations on them, each one atomic transaction (see
`transaction`), are in `labellers`, `runs`, `queries`, `labels` and `metrics`; engines,
sessions and migrations in `db`. Import what you need from here.
"""

from labelqueue.db import (
    DEFAULT_URL,
    check_url,
    make_engine,
    migrate,
    session_factory,
    sqlite_url,
)
from labelqueue.errors import (
    Conflict,
    InvalidTransition,
    LeaseError,
    NotFound,
    QueueError,
    Revoked,
    RunClosed,
)
from labelqueue.export import COLUMNS as EXPORT_COLUMNS
from labelqueue.export import FORMATS as EXPORT_FORMATS
from labelqueue.export import SCHEMA_VERSION as EXPORT_SCHEMA_VERSION
from labelqueue.export import ExportFormat, export_rows, write_export
from labelqueue.instructions import set_instruction
from labelqueue.labellers import (
    authenticate,
    create_labeller,
    find_labeller,
    rotate_token,
    set_labeller_active,
    update_labeller,
)
from labelqueue.labels import consume_labels, labels_for_queries, preferred_segment, submit_label
from labelqueue.metrics import read_metrics, write_metrics
from labelqueue.models import (
    Choice,
    Label,
    Labeller,
    LabelSource,
    Metric,
    MetricStream,
    Preferred,
    Query,
    QueryStatus,
    Role,
    Run,
    RunInstruction,
    RunStatus,
    ShadowChoice,
    TeacherKind,
    Worker,
)
from labelqueue.queries import (
    LEASE_SECONDS,
    cancel_queries,
    lease_next_query,
    push_queries,
    set_clips,
)
from labelqueue.runs import (
    DEAD_WORKER_AFTER_S,
    OPERATOR_MOVES,
    claim_run,
    create_run,
    finish_run,
    heartbeat,
    read_run,
    set_run_status,
    set_teacher,
)

__all__ = [
    "DEAD_WORKER_AFTER_S",
    "DEFAULT_URL",
    "EXPORT_COLUMNS",
    "EXPORT_FORMATS",
    "EXPORT_SCHEMA_VERSION",
    "LEASE_SECONDS",
    "OPERATOR_MOVES",
    "Choice",
    "Conflict",
    "ExportFormat",
    "InvalidTransition",
    "Label",
    "LabelSource",
    "Labeller",
    "LeaseError",
    "Metric",
    "MetricStream",
    "NotFound",
    "Preferred",
    "Query",
    "QueryStatus",
    "QueueError",
    "Revoked",
    "Role",
    "Run",
    "RunClosed",
    "RunStatus",
    "ShadowChoice",
    "TeacherKind",
    "Worker",
    "authenticate",
    "check_url",
    "cancel_queries",
    "claim_run",
    "consume_labels",
    "create_labeller",
    "create_run",
    "export_rows",
    "find_labeller",
    "finish_run",
    "heartbeat",
    "labels_for_queries",
    "lease_next_query",
    "make_engine",
    "migrate",
    "preferred_segment",
    "push_queries",
    "read_metrics",
    "read_run",
    "rotate_token",
    "set_clips",
    "set_labeller_active",
    "set_run_status",
    "sqlite_url",
    "set_teacher",
    "session_factory",
    "submit_label",
    "update_labeller",
    "write_export",
    "write_metrics",
    "RunInstruction",
    "set_instruction",
]
