//! The gRPC service end to end: a real server on a loopback port, a real tonic client.

mod common;

use common::server::TestServer;
use nak::engine::Limits;
use nak::prior::{InteractionPoints, Kelvinlet, NodeCloud, Workspace};
use nak::proto::v1::{self as pb, Grasp, PredictRequest, Vec3};
use tonic::Code;

fn vec3(v: [f32; 3]) -> Option<Vec3> {
    Some(Vec3 {
        x: v[0],
        y: v[1],
        z: v[2],
    })
}

fn node_grasp(nodes: &[u32], u: [f32; 3]) -> Grasp {
    Grasp {
        nodes: nodes.to_vec(),
        displacement: vec3(u),
        ..Default::default()
    }
}

fn f32s(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// Two graspers of ten nodes from grasp regions 3 and 8, as the paper's multi-grasper case.
fn two_graspers(server: &TestServer) -> Vec<Grasp> {
    let m = server.engine.mesh();
    let a: Vec<u32> = m.node_sets["grasp_03"].iter().take(10).copied().collect();
    let b: Vec<u32> = m.node_sets["grasp_08"].iter().take(10).copied().collect();
    vec![
        node_grasp(&a, [0.01, 0.03, -0.01]),
        node_grasp(&b, [-0.02, 0.02, 0.015]),
    ]
}

fn request(grasps: Vec<Grasp>) -> PredictRequest {
    PredictRequest {
        grasps,
        ..Default::default()
    }
}

#[tokio::test]
async fn unary_predict_matches_the_library_prior_bit_for_bit() {
    let server = TestServer::default().await;
    let mut client = server.client().await;
    let grasps = two_graspers(&server);
    let response = client
        .predict(PredictRequest {
            model: "kelvinlet".into(),
            sequence: 41,
            ..request(grasps.clone())
        })
        .await
        .unwrap()
        .into_inner();
    let m = server.engine.mesh().clone();
    assert_eq!(response.sequence, 41);
    assert_eq!(response.node_count as usize, m.node_count());
    assert_eq!(response.interaction_points, 20);
    assert!(response.node_ids.is_empty());
    let timing = response.timing.unwrap();
    assert!(timing.total_us >= timing.prior_us && timing.prior_us > 0.0);

    let mut points = InteractionPoints::default();
    for g in &grasps {
        let u = g.displacement.unwrap();
        for &n in &g.nodes {
            points.push(n, m.positions[n as usize], [u.x as f64, u.y as f64, u.z as f64]);
        }
    }
    let prior = Kelvinlet::new(m.config.prior);
    let mut ws = Workspace::default();
    prior.solve(&points, &mut ws).unwrap();
    let mut expected = vec![0.0f32; 3 * m.node_count()];
    prior.evaluate(
        &ws.coefficients,
        &NodeCloud::new(m.positions.iter().copied()),
        &mut expected,
    );
    // The held nodes answer their grasp's displacement exactly (docs/design.md §7).
    for (&n, u) in points.nodes.iter().zip(&points.displacements) {
        for k in 0..3 {
            expected[3 * n as usize + k] = u[k] as f32;
        }
    }
    let expected_bytes: Vec<u8> = expected.iter().flat_map(|v| v.to_le_bytes()).collect();
    assert_eq!(response.displacements.as_ref(), expected_bytes.as_slice());
    server.stop().await;
}

#[tokio::test]
async fn get_mesh_and_list_models_describe_what_is_served() {
    let server = TestServer::default().await;
    let mut client = server.client().await;
    let mesh = client
        .get_mesh(pb::GetMeshRequest::default())
        .await
        .unwrap()
        .into_inner();
    let m = server.engine.mesh();
    assert_eq!(mesh.node_count as usize, m.node_count());
    assert_eq!(mesh.positions.len(), 12 * m.node_count());
    assert_eq!(mesh.surface_triangles.len(), 12 * m.surface.len());
    assert_eq!(f32s(&mesh.positions)[3], m.positions[1][0] as f32);
    let names: Vec<&str> = mesh.node_sets.iter().map(|s| s.name.as_str()).collect();
    assert!(names.contains(&"fixed"));
    for i in 1..=10 {
        assert!(names.contains(&format!("grasp_{i:02}").as_str()));
    }
    let regions: Vec<&str> = mesh.regions.iter().map(|r| r.name.as_str()).collect();
    assert_eq!(regions, ["liver", "gallbladder", "ducts"]);
    assert_eq!(mesh.content_hash, m.content_hash);

    let unknown = client
        .get_mesh(pb::GetMeshRequest { mesh: "kidney".into() })
        .await
        .unwrap_err();
    assert_eq!(unknown.code(), Code::NotFound);

    let models = client
        .list_models(pb::ListModelsRequest {})
        .await
        .unwrap()
        .into_inner()
        .models;
    let kelvinlet = models.iter().find(|m| m.name == "kelvinlet").expect("kelvinlet listed");
    assert_eq!(kelvinlet.kind, pb::ModelKind::Prior as i32);
    assert_eq!(kelvinlet.mesh, m.content_hash);
    assert_eq!(kelvinlet.metadata["epsilon_m"], "0.05");
    server.stop().await;
}

#[tokio::test]
async fn node_selections_return_rows_of_the_full_field() {
    let server = TestServer::default().await;
    let mut client = server.client().await;
    let grasps = two_graspers(&server);
    let full = client.predict(request(grasps.clone())).await.unwrap().into_inner();
    let full = f32s(&full.displacements);
    let surface = client
        .predict(PredictRequest {
            selection: pb::NodeSelection::Surface as i32,
            ..request(grasps.clone())
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(surface.node_ids, server.engine.mesh().surface_nodes);
    let list = vec![5u32, 0, 1000, 17];
    let listed = client
        .predict(PredictRequest {
            selection: pb::NodeSelection::List as i32,
            nodes: list.clone(),
            ..request(grasps)
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(listed.node_ids, list);
    for (rows, response) in [(&surface.node_ids, &surface), (&listed.node_ids, &listed)] {
        let values = f32s(&response.displacements);
        assert_eq!(values.len(), 3 * rows.len());
        for (i, &n) in rows.iter().enumerate() {
            for k in 0..3 {
                assert_eq!(values[3 * i + k], full[3 * n as usize + k], "node {n}");
            }
        }
    }
    server.stop().await;
}

#[tokio::test]
async fn a_point_grasp_snaps_to_the_surface() {
    let server = TestServer::default().await;
    let mut client = server.client().await;
    let m = server.engine.mesh().clone();
    let target = m.node_sets["grasp_05"][0];
    let p = m.positions[target as usize];
    // A point just outside the surface, radius 0: the nearest surface node.
    let n = m.normals[target as usize];
    let outside = [
        (p[0] + 1e-4 * n[0]) as f32,
        (p[1] + 1e-4 * n[1]) as f32,
        (p[2] + 1e-4 * n[2]) as f32,
    ];
    let response = client
        .predict(request(vec![Grasp {
            point: vec3(outside),
            radius: 0.0,
            displacement: vec3([0.0, 0.02, 0.0]),
            ..Default::default()
        }]))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(response.interaction_points, 1);
    let u = f32s(&response.displacements);
    assert!((u[3 * target as usize + 1] - 0.02).abs() < 1e-7);
    // With a radius, every surface node within it.
    let radius = 0.015f32;
    let within = m
        .surface_nodes
        .iter()
        .filter(|&&s| !m.is_fixed(s))
        .filter(|&&s| {
            let q = m.positions[s as usize];
            (0..3).map(|k| (q[k] - outside[k] as f64).powi(2)).sum::<f64>() <= (radius as f64).powi(2)
        })
        .count();
    let response = client
        .predict(request(vec![Grasp {
            point: vec3(outside),
            radius,
            displacement: vec3([0.0, 0.02, 0.0]),
            ..Default::default()
        }]))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(response.interaction_points as usize, within);
    server.stop().await;
}

#[tokio::test]
async fn streams_answer_every_message_in_order() {
    let server = TestServer::default().await;
    let mut client = server.client().await;
    let grasps = two_graspers(&server);
    let messages: Vec<PredictRequest> = (0..50u64)
        .map(|i| {
            let mut g = grasps.clone();
            g[0].displacement = vec3([0.001 * i as f32, 0.02, 0.0]);
            PredictRequest {
                sequence: 1000 + i,
                ..request(g)
            }
        })
        .collect();
    let mut responses = client
        .predict_stream(tokio_stream::iter(messages.clone()))
        .await
        .unwrap()
        .into_inner();
    let mut seen = Vec::new();
    while let Some(r) = responses.message().await.unwrap() {
        assert!(r.error.is_none());
        seen.push(r);
    }
    assert_eq!(
        seen.iter().map(|r| r.sequence).collect::<Vec<_>>(),
        (1000..1050).collect::<Vec<_>>()
    );
    // Each answer is the unary answer to the same message.
    let unary = client.predict(messages[17].clone()).await.unwrap().into_inner();
    assert_eq!(seen[17].displacements, unary.displacements);
    server.stop().await;
}

#[tokio::test]
async fn a_refused_message_in_a_stream_is_answered_and_the_stream_goes_on() {
    let server = TestServer::default().await;
    let mut client = server.client().await;
    let good = request(two_graspers(&server));
    let bad = request(vec![node_grasp(&[u32::MAX], [0.0, 0.01, 0.0])]);
    let messages = vec![
        PredictRequest {
            sequence: 1,
            ..good.clone()
        },
        PredictRequest { sequence: 2, ..bad },
        PredictRequest { sequence: 3, ..good },
    ];
    let mut responses = client
        .predict_stream(tokio_stream::iter(messages))
        .await
        .unwrap()
        .into_inner();
    let mut all = Vec::new();
    while let Some(r) = responses.message().await.unwrap() {
        all.push(r);
    }
    assert_eq!(all.len(), 3);
    assert!(all[0].error.is_none() && all[2].error.is_none());
    let error = all[1].error.as_ref().expect("second message refused");
    assert_eq!(error.code, Code::InvalidArgument as i32);
    assert!(error.message.contains("4294967295"), "{}", error.message);
    assert_eq!(all[1].sequence, 2);
    assert!(all[1].displacements.is_empty());
    server.stop().await;
}

#[tokio::test]
async fn a_client_that_cancels_its_stream_does_not_disturb_the_server() {
    let server = TestServer::default().await;
    let mut client = server.client().await;
    let good = request(two_graspers(&server));
    let (tx, rx) = tokio::sync::mpsc::channel::<PredictRequest>(4);
    let mut responses = client
        .predict_stream(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    tx.send(PredictRequest {
        sequence: 7,
        ..good.clone()
    })
    .await
    .unwrap();
    assert_eq!(responses.message().await.unwrap().unwrap().sequence, 7);
    // Cancel mid-stream: drop both halves while the server still waits for more.
    drop(responses);
    drop(tx);
    tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    let mut other = server.client().await;
    let after = other.predict(good).await.unwrap().into_inner();
    assert_eq!(after.node_count as usize, server.engine.mesh().node_count());
    server.stop().await;
}

/// Sends a bad request, checks the status code and that the message names the problem, then checks
/// the server still answers a good request.
async fn refused(server: &TestServer, message: PredictRequest, code: Code, mentions: &str) {
    let mut client = server.client().await;
    let status = client.predict(message).await.unwrap_err();
    assert_eq!(status.code(), code, "{}", status.message());
    assert!(
        status.message().contains(mentions),
        "{:?} lacks {mentions:?}",
        status.message()
    );
    let fine = client.predict(request(two_graspers(server))).await;
    assert!(fine.is_ok(), "server stopped serving after a bad request");
}

#[tokio::test]
async fn bad_requests_are_refused_with_the_right_code_and_a_clear_message() {
    let server = TestServer::start(
        Limits {
            max_displacement_m: 0.2,
            max_interaction_points: 256,
            ..Limits::default()
        },
        64 << 10,
    )
    .await;
    let m = server.engine.mesh().clone();
    let surface = m.surface_nodes.iter().copied().find(|&n| !m.is_fixed(n)).unwrap();
    let inside = (0..m.node_count() as u32).find(|&n| !m.is_surface[n as usize]).unwrap();
    let fixed = m.node_sets["fixed"][0];
    let ok = |u: [f32; 3]| node_grasp(&[surface], u);

    let unknown_model = PredictRequest {
        model: "pointnet".into(),
        ..request(vec![ok([0.0, 0.01, 0.0])])
    };
    refused(&server, unknown_model, Code::NotFound, "unknown model \"pointnet\"").await;
    let unknown_mesh = PredictRequest {
        mesh: "kidney".into(),
        ..request(vec![ok([0.0, 0.01, 0.0])])
    };
    refused(&server, unknown_mesh, Code::NotFound, "mesh \"kidney\"").await;
    refused(&server, request(vec![]), Code::InvalidArgument, "no grasps").await;
    let n = m.node_count() as u32;
    refused(
        &server,
        request(vec![node_grasp(&[n], [0.0, 0.01, 0.0])]),
        Code::InvalidArgument,
        &format!("node {n}"),
    )
    .await;
    refused(
        &server,
        request(vec![node_grasp(&[inside], [0.0, 0.01, 0.0])]),
        Code::InvalidArgument,
        "inside the organ",
    )
    .await;
    refused(
        &server,
        request(vec![node_grasp(&[fixed], [0.0, 0.01, 0.0])]),
        Code::InvalidArgument,
        &format!("node {fixed}, which is in the mesh's `fixed` set"),
    )
    .await;
    refused(
        &server,
        request(vec![ok([f32::NAN, 0.0, 0.0])]),
        Code::InvalidArgument,
        "not finite",
    )
    .await;
    refused(
        &server,
        request(vec![ok([0.0, f32::INFINITY, 0.0])]),
        Code::InvalidArgument,
        "not finite",
    )
    .await;
    let nan_point = Grasp {
        point: vec3([0.0, f32::NAN, 0.0]),
        displacement: vec3([0.0, 0.01, 0.0]),
        ..Default::default()
    };
    refused(&server, request(vec![nan_point]), Code::InvalidArgument, "not a finite").await;
    refused(
        &server,
        request(vec![ok([0.0, 0.25, 0.0])]),
        Code::InvalidArgument,
        "above the server's bound of 200.0 mm",
    )
    .await;
    let many: Vec<u32> = m
        .surface_nodes
        .iter()
        .copied()
        .filter(|&n| !m.is_fixed(n))
        .take(257)
        .collect();
    refused(
        &server,
        request(vec![node_grasp(&many, [0.0, 0.01, 0.0])]),
        Code::InvalidArgument,
        "more than 256",
    )
    .await;
    let conflicting = vec![
        node_grasp(&[surface], [0.0, 0.01, 0.0]),
        node_grasp(&[surface], [0.0, 0.02, 0.0]),
    ];
    refused(
        &server,
        request(conflicting),
        Code::InvalidArgument,
        &format!("node {surface} is held by two grasps"),
    )
    .await;
    let huge: Vec<u32> = (0..40_000).collect();
    refused(
        &server,
        request(vec![node_grasp(&huge, [0.0, 0.01, 0.0])]),
        Code::ResourceExhausted,
        "too large",
    )
    .await;
    server.stop().await;
}

#[tokio::test]
async fn malformed_grasps_and_node_selections_are_refused_naming_the_field() {
    let server = TestServer::start(Limits::default(), 64 << 10).await;
    let m = server.engine.mesh().clone();
    let surface = m.surface_nodes.iter().copied().find(|&n| !m.is_fixed(n)).unwrap();
    let u = vec3([0.0, 0.01, 0.0]);
    let malformed = [
        (
            Grasp {
                nodes: vec![surface],
                point: vec3([0.0, 0.0, 0.0]),
                displacement: u,
                ..Default::default()
            },
            "grasps[0] gives both nodes and a point",
        ),
        (
            Grasp {
                displacement: u,
                ..Default::default()
            },
            "grasps[0] holds nothing",
        ),
        (
            Grasp {
                point: vec3([0.0, 0.0, 0.0]),
                radius: -0.01,
                displacement: u,
                ..Default::default()
            },
            "non-negative distance",
        ),
        (
            Grasp {
                point: vec3([10.0, 10.0, 10.0]),
                radius: 0.005,
                displacement: u,
                ..Default::default()
            },
            "no free surface node lies within 5.0 mm",
        ),
    ];
    for (grasp, mentions) in malformed {
        refused(&server, request(vec![grasp]), Code::InvalidArgument, mentions).await;
    }

    let n = m.node_count() as u32;
    let selections = [
        (99, vec![], "unknown node selection 99".to_owned()),
        (
            pb::NodeSelection::List as i32,
            vec![],
            "the node selection is an empty list".to_owned(),
        ),
        (
            pb::NodeSelection::List as i32,
            vec![0, n + 5],
            format!("selected node {} does not exist", n + 5),
        ),
    ];
    for (selection, nodes, mentions) in selections {
        let message = PredictRequest {
            selection,
            nodes,
            ..request(vec![node_grasp(&[surface], [0.0, 0.01, 0.0])])
        };
        refused(&server, message, Code::InvalidArgument, &mentions).await;
    }
    server.stop().await;
}

#[tokio::test]
async fn an_oversize_message_in_a_stream_is_resource_exhausted() {
    let server = TestServer::start(Limits::default(), 64 << 10).await;
    let mut client = server.client().await;
    let huge: Vec<u32> = (0..40_000).collect();
    let messages = vec![request(vec![node_grasp(&huge, [0.0, 0.01, 0.0])])];
    let result = client.predict_stream(tokio_stream::iter(messages)).await;
    let status = match result {
        Ok(response) => response.into_inner().message().await.unwrap_err(),
        Err(status) => status,
    };
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    let fine = client.predict(request(two_graspers(&server))).await;
    assert!(fine.is_ok());
    server.stop().await;
}

#[tokio::test]
async fn health_checking_reports_the_service_as_serving() {
    use tonic_health::pb::health_client::HealthClient;
    use tonic_health::pb::{HealthCheckRequest, health_check_response::ServingStatus};
    let server = TestServer::default().await;
    let channel = tonic::transport::Channel::from_shared(format!("http://{}", server.address))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut health = HealthClient::new(channel);
    let status = health
        .check(HealthCheckRequest {
            service: "nak.v1.Deformation".into(),
        })
        .await
        .unwrap()
        .into_inner()
        .status;
    assert_eq!(status, ServingStatus::Serving as i32);
    server.stop().await;
}

#[tokio::test]
async fn server_reflection_lists_the_deformation_service() {
    use tonic_reflection::pb::v1::ServerReflectionRequest;
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    let server = TestServer::default().await;
    let channel = tonic::transport::Channel::from_shared(format!("http://{}", server.address))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut reflection = ServerReflectionClient::new(channel);
    let ask = ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut answers = reflection
        .server_reflection_info(tokio_stream::iter([ask]))
        .await
        .unwrap()
        .into_inner();
    let answer = answers.message().await.unwrap().unwrap();
    let Some(MessageResponse::ListServicesResponse(list)) = answer.message_response else {
        panic!("unexpected answer {answer:?}");
    };
    let names: Vec<String> = list.service.into_iter().map(|s| s.name).collect();
    assert!(names.contains(&"nak.v1.Deformation".to_owned()), "{names:?}");
    assert!(names.contains(&"grpc.health.v1.Health".to_owned()), "{names:?}");
    server.stop().await;
}

/// Prior-only requests over few node–point pairs are computed on the connection's thread; more
/// interaction points or more nodes go to the pool.
#[test]
fn the_engine_calls_small_prior_requests_quick() {
    use nak::engine::{Engine, Request, Selection};
    let mesh = std::sync::Arc::new(nak::mesh::load(&nak::mesh::MeshSource::Embedded).unwrap());
    let engine = Engine::new(mesh.clone(), Limits::default());
    let grasping = |points: usize, selection: Selection| {
        let request = Request {
            grasps: vec![nak::engine::Grasp {
                nodes: mesh
                    .surface_nodes
                    .iter()
                    .copied()
                    .filter(|&n| !mesh.is_fixed(n))
                    .take(points)
                    .collect(),
                displacement: [0.0, 0.01, 0.0],
                ..Default::default()
            }],
            selection,
            ..Default::default()
        };
        let prepared = engine.prepare(&request).unwrap();
        engine.is_quick(&prepared, &request)
    };
    let most = Limits::default().quick_terms / mesh.node_count();
    assert!(grasping(20, Selection::All));
    assert!(grasping(most, Selection::All));
    assert!(!grasping(most + 1, Selection::All));
    // The surface alone has fewer nodes, so more points stay quick.
    assert!(grasping(most + 1, Selection::Surface));
    let pooled = Engine::new(
        mesh.clone(),
        Limits {
            quick_terms: 0,
            ..Limits::default()
        },
    );
    let request = Request {
        grasps: vec![nak::engine::Grasp {
            nodes: mesh
                .surface_nodes
                .iter()
                .copied()
                .filter(|&n| !mesh.is_fixed(n))
                .take(1)
                .collect(),
            ..Default::default()
        }],
        ..Default::default()
    };
    assert!(!pooled.is_quick(&pooled.prepare(&request).unwrap(), &request));
}
