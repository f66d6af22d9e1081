//! The wire: decoding a PredictRequest (two graspers, K = 20) and encoding a PredictResponse carrying
//! the full field of the phantom (9,701 nodes, 116 kB), as tonic does for every call. The field is
//! wrapped without copying when the response is built; encoding copies it once into the frame.

use bytes::BytesMut;
use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use nak::proto::v1::{Grasp, PredictRequest, PredictResponse, Timing, Vec3};
use nak::wire::f32_bytes;
use prost::Message;

fn codec(c: &mut Criterion) {
    let grasp = |first: u32| Grasp {
        nodes: (first..first + 10).collect(),
        displacement: Some(Vec3 {
            x: 0.01,
            y: 0.02,
            z: -0.01,
        }),
        ..Default::default()
    };
    let request = PredictRequest {
        model: "kelvinlet".into(),
        grasps: vec![grasp(1200), grasp(3400)],
        sequence: 7,
        ..Default::default()
    };
    let encoded_request = request.encode_to_vec();
    let nodes = 9_701usize;
    let field: Vec<f32> = (0..3 * nodes).map(|i| i as f32 * 1e-6).collect();

    let mut group = c.benchmark_group("codec");
    group.throughput(Throughput::Bytes(encoded_request.len() as u64));
    group.bench_function("decode_request_k20", |b| {
        b.iter(|| PredictRequest::decode(encoded_request.as_slice()).expect("valid request"))
    });
    group.throughput(Throughput::Bytes((12 * nodes) as u64));
    let response = PredictResponse {
        sequence: 7,
        node_count: nodes as u32,
        displacements: f32_bytes(field),
        timing: Some(Timing::default()),
        model: "kelvinlet".into(),
        interaction_points: 20,
        ..Default::default()
    };
    let mut buffer = BytesMut::with_capacity(response.encoded_len());
    group.bench_function("encode_response_full_field", |b| {
        b.iter(|| {
            buffer.clear();
            response.encode(&mut buffer).expect("buffer has room");
        })
    });
    group.finish();
}

criterion_group!(benches, codec);
criterion_main!(benches);
