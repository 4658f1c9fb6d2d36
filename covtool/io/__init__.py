"""File input/output at the edges: TOML, CSV, workbooks, figures."""
