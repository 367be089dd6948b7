-- An asset's jobs, newest first (`GET /v1/assets/{id}/jobs`: the console lists them on the
-- asset's page, so a job started there can be found again after leaving the page).
CREATE INDEX jobs_asset ON jobs(asset_id, created_at);
