"""A run's configuration: the schema (`schema`: frozen dataclasses, one parser of a field's
value), the presets and JSON files (`presets`), and the command line (`args`). Its public names
are importable from here."""

from runvocab.config.args import ALIASES, add_config_arguments, overrides_from_args
from runvocab.config.presets import (
    ALGO_PRESETS,
    ALGO_TASK_PRESETS,
    FAMILY_PRESETS,
    PRESETS,
    SURF,
    TASK_PRESETS,
    WRITTEN_WHEN_SET,
    apply_overrides,
    build_config,
    from_dict,
    load_json,
    preset_layers,
    save_json,
    to_dict,
)
from runvocab.config.schema import (
    BOOL_WORDS,
    FeedbackConfig,
    RewardConfig,
    RunConfig,
    SACConfig,
    SkillConfig,
    TeacherConfig,
    parse_value,
    typed_overrides,
)

__all__ = [
    "ALGO_PRESETS", "ALGO_TASK_PRESETS", "ALIASES", "BOOL_WORDS", "FAMILY_PRESETS", "PRESETS",
    "SURF", "TASK_PRESETS", "WRITTEN_WHEN_SET", "FeedbackConfig", "RewardConfig", "RunConfig",
    "SACConfig", "SkillConfig", "TeacherConfig", "add_config_arguments", "apply_overrides",
    "build_config", "from_dict", "load_json", "overrides_from_args", "parse_value",
    "preset_layers", "save_json", "to_dict", "typed_overrides",
]
