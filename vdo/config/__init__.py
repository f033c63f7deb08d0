"""The experiment file: one schema of rows (name, kind, unit, default, doc) that parses, checks and
documents every table, and the `Experiment` it builds. Imports no JAX, Mitsuba or matplotlib."""
