"""What every step runs on: configuration (config) and its checks (schema), the step entry point (entry), the fork
server a step starts from (forkserver), atomic files (io), safe loading (safe_load), code digests (provenance), error
types (errors), MLflow tracking (tracking) and its dashboard (dashboard)."""
