"""Pipeline stages: each a function (workspace, config) -> outputs in its numbered folder."""
