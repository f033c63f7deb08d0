"""Write docs/config.md from the schema of vdo/config/ (`vdo.config.reference.markdown`; run from the repository root)."""

from pathlib import Path

from vdo.config.reference import markdown

if __name__ == "__main__":
    Path(__file__).resolve().parents[1].joinpath("docs", "config.md").write_text(markdown())
