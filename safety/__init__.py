"""Host-side safety: supervisor, geofence, watchdogs (issue 6)."""
