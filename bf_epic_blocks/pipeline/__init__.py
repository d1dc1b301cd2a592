"""The pipeline room: YAML pipeline configs, config -> graph of blocks, and the ``bf-epic`` CLI.

Modules: :mod:`.config` (schema and validation), :mod:`.runner` (plan and run a validated config as
a graph of blocks), :mod:`.cli`. Nothing below this room imports it.
"""
