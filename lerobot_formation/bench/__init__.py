"""The evaluation engine (``evaluation``, ``controllers``), scene sets, results, tables, figures, the bench CLI and the demo."""
