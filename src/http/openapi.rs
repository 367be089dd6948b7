//! `GET /openapi.json` — the committed `api/openapi.yaml`, served as JSON.

use std::sync::OnceLock;

use axum::Json;
use axum::response::{IntoResponse, Response};

use super::error::ApiError;

/// The spec as committed.
pub const YAML: &str = include_str!("../../api/openapi.yaml");

/// The spec as JSON (parsed once).
pub fn spec() -> Result<&'static serde_json::Value, String> {
    static SPEC: OnceLock<Result<serde_json::Value, String>> = OnceLock::new();
    SPEC.get_or_init(|| serde_yaml_ng::from_str(YAML).map_err(|e| e.to_string()))
        .as_ref()
        .map_err(Clone::clone)
}

/// `GET /openapi.json`.
pub async fn json() -> Response {
    match spec() {
        Ok(v) => Json(v).into_response(),
        Err(e) => {
            ApiError::internal(format!("api/openapi.yaml does not parse: {e}")).into_response()
        }
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;

    #[test]
    fn the_spec_lists_exactly_the_routes_the_router_serves() {
        let spec = super::spec().unwrap();
        let mut in_spec = BTreeSet::new();
        for (path, item) in spec["paths"].as_object().unwrap() {
            for method in item.as_object().unwrap().keys() {
                if ["get", "post", "put", "delete", "patch"].contains(&method.as_str()) {
                    in_spec.insert((method.clone(), path.clone()));
                }
            }
        }
        let served: BTreeSet<(String, String)> = super::super::ROUTES
            .iter()
            .map(|(m, p)| (m.to_string(), p.to_string()))
            .collect();
        assert_eq!(in_spec, served);
    }
}
