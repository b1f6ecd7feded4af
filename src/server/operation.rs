//! Every operation of the API, the access its key needs, and how each transport names it: the one table the
//! key check reads. Both transports check the key for a request's operation before anything reads its body
//! (HTTP: the `authorize` middleware of [`crate::server::http`]; gRPC: [`crate::server::grpc::GateLayer`]) and
//! hand the proof ([`crate::server::auth::Authorized`]) to the handler.

use crate::settings::Access;

/// An operation of the API (a gRPC method, and its HTTP twin where it has one).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Operation {
    CreateMap,
    GetMap,
    ListMaps,
    DeleteMap,
    MapContents,
    AddKeyframes,
    RemoveKeyframe,
    MergeMaps,
    ExportMap,
    ImportMap,
    Describe,
    MatchPair,
    Localize,
    LocalizeTrack,
}

use Operation::*;

/// Every operation, for tests that walk the table.
pub const ALL: [Operation; 14] = [
    CreateMap,
    GetMap,
    ListMaps,
    DeleteMap,
    MapContents,
    AddKeyframes,
    RemoveKeyframe,
    MergeMaps,
    ExportMap,
    ImportMap,
    Describe,
    MatchPair,
    Localize,
    LocalizeTrack,
];

impl Operation {
    /// The name in logs, metrics and error messages: the gRPC method's (one keyframe posted over HTTP is the
    /// AddKeyframes stream's operation).
    pub fn name(self) -> &'static str {
        match self {
            CreateMap => "CreateMap",
            GetMap => "GetMap",
            ListMaps => "ListMaps",
            DeleteMap => "DeleteMap",
            MapContents => "MapContents",
            AddKeyframes => "AddKeyframes",
            RemoveKeyframe => "RemoveKeyframe",
            MergeMaps => "MergeMaps",
            ExportMap => "ExportMap",
            ImportMap => "ImportMap",
            Describe => "Describe",
            MatchPair => "MatchPair",
            Localize => "Localize",
            LocalizeTrack => "LocalizeTrack",
        }
    }

    /// What the key must allow: reads change nothing.
    pub fn access(self) -> Access {
        match self {
            GetMap | ListMaps | MapContents | ExportMap | Describe | MatchPair | Localize | LocalizeTrack => {
                Access::Read
            }
            CreateMap | DeleteMap | AddKeyframes | RemoveKeyframe | MergeMaps | ImportMap => Access::Write,
        }
    }

    /// The operation of a gRPC method path (`/scone.v1.Maps/CreateMap`); `None` for other services (health,
    /// reflection) and unknown methods (tonic answers UNIMPLEMENTED).
    pub fn from_grpc_path(path: &str) -> Option<Self> {
        Some(match path {
            "/scone.v1.Maps/CreateMap" => CreateMap,
            "/scone.v1.Maps/GetMap" => GetMap,
            "/scone.v1.Maps/ListMaps" => ListMaps,
            "/scone.v1.Maps/DeleteMap" => DeleteMap,
            "/scone.v1.Maps/AddKeyframes" => AddKeyframes,
            "/scone.v1.Maps/RemoveKeyframe" => RemoveKeyframe,
            "/scone.v1.Maps/MergeMaps" => MergeMaps,
            "/scone.v1.Maps/ExportMap" => ExportMap,
            "/scone.v1.Maps/ImportMap" => ImportMap,
            "/scone.v1.Matching/Describe" => Describe,
            "/scone.v1.Matching/MatchPair" => MatchPair,
            "/scone.v1.Matching/Localize" => Localize,
            "/scone.v1.Matching/LocalizeTrack" => LocalizeTrack,
            _ => return None,
        })
    }

    /// The operation of an HTTP route (method and the route's path pattern, as axum's `MatchedPath` gives
    /// it); `None` for routes that are not API operations (health, metrics, the document, the console).
    pub fn from_http(method: &str, route: &str) -> Option<Self> {
        Some(match (method, route) {
            ("POST", "/v1/maps") => CreateMap,
            ("GET", "/v1/maps") => ListMaps,
            ("GET", "/v1/maps/{map_id}") => GetMap,
            ("DELETE", "/v1/maps/{map_id}") => DeleteMap,
            ("GET", "/v1/maps/{map_id}/contents") => MapContents,
            ("POST", "/v1/maps/{map_id}/keyframes") => AddKeyframes,
            ("DELETE", "/v1/maps/{map_id}/keyframes/{keyframe_id}") => RemoveKeyframe,
            ("POST", "/v1/maps/{map_id}/merge") => MergeMaps,
            ("GET", "/v1/maps/{map_id}/export") => ExportMap,
            ("POST", "/v1/maps/{map_id}/import") => ImportMap,
            ("POST", "/v1/describe") => Describe,
            ("POST", "/v1/match") => MatchPair,
            ("POST", "/v1/maps/{map_id}/localize") => Localize,
            ("POST", "/v1/maps/{map_id}/localize-track") => LocalizeTrack,
            _ => return None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_change_nothing_and_every_write_needs_a_write_key() {
        let writes: Vec<_> = ALL.iter().filter(|o| o.access() == Access::Write).map(|o| o.name()).collect();
        assert_eq!(writes, ["CreateMap", "DeleteMap", "AddKeyframes", "RemoveKeyframe", "MergeMaps", "ImportMap"]);
    }

    /// Every rpc of the proto's services is an operation whose name is the method's, and back: a new rpc
    /// without an entry here would reach its method without a key check (and be refused as internal).
    #[test]
    fn every_rpc_is_an_operation() {
        let proto = include_str!("../../proto/scone/v1/scone.proto");
        let mut service = "";
        let mut paths = Vec::new();
        for line in proto.lines().map(str::trim) {
            if let Some(rest) = line.strip_prefix("service ") {
                service = rest.split_whitespace().next().unwrap_or("");
            } else if let Some(rest) = line.strip_prefix("rpc ") {
                let method = rest.split('(').next().unwrap_or("").trim();
                paths.push((format!("/scone.v1.{service}/{method}"), method.to_string()));
            }
        }
        assert_eq!(paths.len(), 13);
        for (path, method) in &paths {
            let op = Operation::from_grpc_path(path).unwrap_or_else(|| panic!("{path} is not an operation"));
            assert_eq!(op.name(), method);
        }
        assert!(Operation::from_grpc_path("/grpc.health.v1.Health/Check").is_none());
    }

    /// Every operation is served over at least one transport.
    #[test]
    fn every_operation_has_a_route_or_a_method() {
        let routes = [
            ("POST", "/v1/maps"),
            ("GET", "/v1/maps"),
            ("GET", "/v1/maps/{map_id}"),
            ("DELETE", "/v1/maps/{map_id}"),
            ("GET", "/v1/maps/{map_id}/contents"),
            ("POST", "/v1/maps/{map_id}/keyframes"),
            ("DELETE", "/v1/maps/{map_id}/keyframes/{keyframe_id}"),
            ("POST", "/v1/maps/{map_id}/merge"),
            ("GET", "/v1/maps/{map_id}/export"),
            ("POST", "/v1/maps/{map_id}/import"),
            ("POST", "/v1/describe"),
            ("POST", "/v1/match"),
            ("POST", "/v1/maps/{map_id}/localize"),
            ("POST", "/v1/maps/{map_id}/localize-track"),
        ];
        for op in ALL {
            assert!(routes.iter().any(|(m, r)| Operation::from_http(m, r) == Some(op)), "{op:?} has no route");
        }
    }

    #[test]
    fn names_are_distinct() {
        let mut names: Vec<_> = ALL.iter().map(|o| o.name()).collect();
        names.sort();
        names.dedup();
        assert_eq!(names.len(), ALL.len());
    }
}
