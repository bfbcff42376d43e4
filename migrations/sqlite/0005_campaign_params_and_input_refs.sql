-- Estimation parameters stored once per campaign instead of in every task's input: executors
-- read them from here (once per campaign and process) for tasks whose input does not carry them.
-- Campaigns created before keep working: their tasks still carry the parameters, and the column
-- is filled from the manifest they were submitted with.
ALTER TABLE campaigns ADD COLUMN params TEXT;
UPDATE campaigns SET params = json_extract(spec, '$.parameters')
    WHERE json_valid(spec) AND json_type(spec, '$.parameters') = 'object';
-- Which campaigns name an input object: deleting a campaign removes the inputs it alone named,
-- and an input named by a campaign cannot be deleted.
CREATE INDEX strips_uri ON strips (uri);
CREATE INDEX trajectories_uri ON trajectories (uri);
