//! In-process orchestration of a campaign: ingest, tiles, iterations, export, report.
