"""Flight data from outside cfknode (CSV, Parquet) as training segments; see docs/data.md."""
