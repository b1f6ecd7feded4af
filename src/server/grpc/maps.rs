//! The `scone.v1.Maps` service: create, list, get, delete, keyframes (a stream), merge, export and import.

use std::pin::Pin;

use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};

use super::api::{authorized, GrpcApi};
use super::convert::{convention, external_landmarks, frame_input, invalid, map_info, similarity_out, to_status};
use crate::camera::Pose;
use crate::server::app::{MapId, NoMap};
use crate::server::proto;
use crate::service::{KeyframeRequest, ServiceError, Similarity};

/// Export chunks, bytes.
const CHUNK: usize = 1 << 20;

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send + 'static>>;

#[tonic::async_trait]
impl proto::maps_server::Maps for GrpcApi {
    async fn create_map(&self, req: Request<proto::CreateMapRequest>) -> Result<Response<proto::MapInfo>, Status> {
        let authorized = authorized(&req)?;
        let id = req.into_inner().map_id;
        let s = self.call(authorized, NoMap, move |a, ()| a.service.create_map(&id)).await?;
        Ok(Response::new(map_info(s)))
    }

    async fn get_map(&self, req: Request<proto::GetMapRequest>) -> Result<Response<proto::MapInfo>, Status> {
        let authorized = authorized(&req)?;
        let id = req.into_inner().map_id;
        let s = self.call(authorized, MapId(id), |_, map| Ok(map.summary())).await?;
        Ok(Response::new(map_info(s)))
    }

    async fn list_maps(
        &self,
        req: Request<proto::ListMapsRequest>,
    ) -> Result<Response<proto::ListMapsResponse>, Status> {
        let listing = self.call(authorized(&req)?, NoMap, |a, ()| a.service.list_maps()).await?;
        Ok(Response::new(proto::ListMapsResponse {
            maps: listing.maps.into_iter().map(map_info).collect(),
            held_back: listing
                .held_back
                .into_iter()
                .map(|(map_id, reason)| proto::HeldBackMap { map_id, reason })
                .collect(),
        }))
    }

    async fn delete_map(
        &self,
        req: Request<proto::DeleteMapRequest>,
    ) -> Result<Response<proto::DeleteMapResponse>, Status> {
        let authorized = authorized(&req)?;
        let id = req.into_inner().map_id;
        self.call(authorized, NoMap, move |a, ()| a.service.delete_map(&id)).await?;
        Ok(Response::new(proto::DeleteMapResponse {}))
    }

    type AddKeyframesStream = ReceiverStream<Result<proto::KeyframeAck, Status>>;

    async fn add_keyframes(
        &self,
        req: Request<Streaming<proto::AddKeyframeRequest>>,
    ) -> Result<Response<Self::AddKeyframesStream>, Status> {
        let authorized = authorized(&req)?;
        let mut inbound = req.into_inner();
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        let api = self.clone();
        tokio::spawn(async move {
            loop {
                let msg = match api.next_message(&mut inbound).await {
                    Ok(Some(m)) => m,
                    Ok(None) => break,
                    Err(s) => {
                        let _ = tx.send(Err(s)).await;
                        break;
                    }
                };
                let map = MapId(msg.map_id.clone());
                let r = api
                    .call(authorized, map, move |a, map| {
                        let p = msg.pose.ok_or_else(|| invalid("pose", "is required"))?;
                        let request = KeyframeRequest {
                            id: msg.keyframe_id,
                            frame: frame_input(msg.frame, "frame")?,
                            pose: Pose { translation: [p.tx, p.ty, p.tz], rotation: [p.qx, p.qy, p.qz, p.qw] },
                            convention: convention(msg.pose_convention)?,
                            depth_png: (!msg.depth_png.is_empty()).then_some(msg.depth_png),
                            depth_scale: (msg.depth_scale != 0.0).then_some(msg.depth_scale),
                            external_landmarks: external_landmarks(msg.external_landmarks)?,
                        };
                        let (added, times) = a.service.add_keyframe(&map, request)?;
                        a.metrics.stages(&times);
                        Ok(proto::KeyframeAck {
                            keyframe_id: added.keyframe,
                            new_landmarks: added.new_landmarks as u64,
                            observations: added.observations as u64,
                            map_version: added.version,
                            external_rejected: added.external.rejected as u64,
                            external_unassociated: added.external.unassociated as u64,
                        })
                    })
                    .await;
                let failed = r.is_err();
                if tx.send(r).await.is_err() || failed {
                    break;
                }
            }
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    async fn remove_keyframe(
        &self,
        req: Request<proto::RemoveKeyframeRequest>,
    ) -> Result<Response<proto::MapInfo>, Status> {
        let authorized = authorized(&req)?;
        let r = req.into_inner();
        let keyframe = r.keyframe_id;
        let s = self.call(authorized, MapId(r.map_id), move |a, map| a.service.remove_keyframe(&map, keyframe)).await?;
        Ok(Response::new(map_info(s)))
    }

    async fn merge_maps(
        &self,
        req: Request<proto::MergeMapsRequest>,
    ) -> Result<Response<proto::MergeMapsResponse>, Status> {
        let authorized = authorized(&req)?;
        let r = req.into_inner();
        let target = MapId(r.target_map_id.clone());
        let o = self
            .call(authorized, target, move |a, map| {
                let transform = r.transform.map(|t| Similarity {
                    translation: [t.tx, t.ty, t.tz],
                    rotation: [t.qx, t.qy, t.qz, t.qw],
                    scale: t.scale,
                });
                a.service.merge_maps(&map, &r.source_map_id, transform)
            })
            .await?;
        Ok(Response::new(proto::MergeMapsResponse {
            target: Some(map_info(o.target)),
            transform: Some(similarity_out(&o.transform)),
            transform_estimated: o.estimated,
            source_keyframes: o.source_keyframes as u32,
            keyframes_localised: o.localised as u32,
            transform_inliers: o.inliers as u32,
            keyframe_id_offset: o.keyframe_id_offset,
            landmarks_fused: o.landmarks_fused as u64,
            landmarks_added: o.landmarks_added as u64,
        }))
    }

    type ExportMapStream = BoxStream<proto::MapChunk>;

    async fn export_map(
        &self,
        req: Request<proto::ExportMapRequest>,
    ) -> Result<Response<Self::ExportMapStream>, Status> {
        let authorized = authorized(&req)?;
        let id = req.into_inner().map_id;
        let bytes = self.call(authorized, MapId(id), |a, map| a.service.export_map(&map)).await?;
        let chunks: Vec<Result<proto::MapChunk, Status>> =
            bytes.chunks(CHUNK).map(|c| Ok(proto::MapChunk { map_id: String::new(), data: c.to_vec() })).collect();
        Ok(Response::new(Box::pin(tokio_stream::iter(chunks))))
    }

    async fn import_map(&self, req: Request<Streaming<proto::MapChunk>>) -> Result<Response<proto::MapInfo>, Status> {
        let authorized = authorized(&req)?;
        let max = self.app.settings.server.max_map_bytes;
        let mut inbound = req.into_inner();
        let mut id = String::new();
        let mut bytes = Vec::new();
        while let Some(chunk) = self.next_message(&mut inbound).await? {
            if id.is_empty() {
                id = chunk.map_id;
            }
            if bytes.len() + chunk.data.len() > max {
                return Err(to_status(&ServiceError::TooLarge { what: "the map file".into(), limit: max }));
            }
            bytes.extend_from_slice(&chunk.data);
        }
        let s = self
            .call(authorized, NoMap, move |a, ()| {
                if id.is_empty() {
                    return Err(invalid("map_id", "the first chunk must name the map"));
                }
                a.service.import_map(&id, &bytes)
            })
            .await?;
        Ok(Response::new(map_info(s)))
    }
}
