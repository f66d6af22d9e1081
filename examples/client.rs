//! A minimal nak client: fetch the mesh, lift grasp region 4 by 2 cm, print what came back (the
//! field's reach, the server's time and, from models that give them, the grasper's force).
//!
//! Start a server (`cargo run --release -- serve`), then `cargo run --release --example client [URLS [MODEL]]`.
//! URLS: one server or several, comma-separated (or a name resolving to several, a Kubernetes headless
//! Service): requests are spread over all of them. MODEL defaults to the most accurate network shipped
//! with the phantom; `kelvinlet` is the prior alone. For a server with TLS and a token, set
//! NAK_TLS_CA (PEM) and NAK_AUTH_TOKEN_FILE.

use nak::client::{ClientConfig, connect};
use nak::proto::v1::{GetMeshRequest, Grasp, PredictRequest, Vec3};

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let target = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "http://127.0.0.1:50051".into());
    let model = std::env::args().nth(2).unwrap_or_else(|| "pod-res-big".into());
    let config = ClientConfig {
        tls_ca: std::env::var_os("NAK_TLS_CA").map(Into::into),
        auth_token_file: std::env::var_os("NAK_AUTH_TOKEN_FILE").map(Into::into),
        ..ClientConfig::new(target)
    };
    let mut client = connect(&config).await?;
    let mesh = client.get_mesh(GetMeshRequest::default()).await?.into_inner();
    let grasp_04 = mesh
        .node_sets
        .iter()
        .find(|s| s.name == "grasp_04")
        .ok_or_else(|| anyhow::anyhow!("the mesh has no grasp_04"))?;
    let request = PredictRequest {
        model,
        grasps: vec![Grasp {
            nodes: grasp_04.nodes.iter().take(10).copied().collect(),
            displacement: Some(Vec3 {
                x: 0.0,
                y: 0.02,
                z: 0.0,
            }),
            ..Default::default()
        }],
        ..Default::default()
    };
    for _ in 0..5 {
        let started = std::time::Instant::now();
        let response = client.predict(request.clone()).await?.into_inner();
        let round_trip = started.elapsed();
        // Packed little-endian f32, (node_count, 3).
        let u: Vec<f32> = response
            .displacements
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        let largest = u
            .chunks(3)
            .map(|d| (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt())
            .fold(0.0, f32::max);
        let t = response.timing.unwrap_or_default();
        println!(
            "{} nodes, largest displacement {:.1} mm; server {:.0} µs (prior {:.0} µs), round trip {:.0} µs",
            response.node_count,
            largest * 1e3,
            t.total_us,
            t.prior_us,
            round_trip.as_secs_f64() * 1e6
        );
        // Empty when the model gives no forces (ListModels says which do).
        for f in &response.grasp_forces {
            println!(
                "  the grasper exerts ({:+.3}, {:+.3}, {:+.3}) N on the tissue",
                f.x, f.y, f.z
            );
        }
    }
    Ok(())
}
