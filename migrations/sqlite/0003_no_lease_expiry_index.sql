-- Dropped with the PostgreSQL migration of the same name: one index fewer to update per claim; the
-- reconciler finds expired leases through `tasks_open`.
DROP INDEX tasks_leased;
