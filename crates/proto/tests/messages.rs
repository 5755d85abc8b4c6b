//! Messages round-trip through encode/decode, and the wire form of a few is pinned.

use pathfarm_proto::v1::{
    self, coordinator_message, data_chunk, job_settings, lease, tile_upload, worker_message,
};
use pathfarm_proto::{MAX_CHUNK_BYTES, PROTOCOL_VERSION};
use prost::Message;

fn digest(byte: u8) -> Vec<u8> {
    vec![byte; pathfarm_proto::DIGEST_BYTES]
}

fn sample_lease() -> v1::Lease {
    v1::Lease {
        lease_id: 0x1234_5678_9abc,
        job_id: "job-42".into(),
        deadline_unix_ms: 1_767_225_600_000,
        attempt: 2,
        tile: Some(v1::Rect {
            x0: 64,
            y0: 32,
            x1: 128,
            y1: 96,
        }),
        scene: Some(lease::Scene::Bundle(v1::Bundle {
            root: "scene.xml".into(),
            files: vec![
                v1::BundleFile {
                    path: "scene.xml".into(),
                    digest: digest(0xab),
                    size: 4096,
                },
                v1::BundleFile {
                    path: "meshes/bunny.ply".into(),
                    digest: digest(0xcd),
                    size: 35 << 20,
                },
            ],
        })),
        settings: Some(v1::SceneSettings {
            integrator: Some("guided_path".into()),
            defines: vec![v1::Define {
                name: "spp".into(),
                value: "64".into(),
            }],
            resolution: Some(v1::Resolution {
                width: 640,
                height: 360,
            }),
            seed: Some(7),
        }),
        image: Some(v1::Resolution {
            width: 640,
            height: 360,
        }),
        pass: Some(v1::PassSpec {
            unit: 5,
            iteration: 3,
            kind: v1::PassKind::Record as i32,
            first_sample: 60,
            spp: 8,
            passes: 2,
            guide: true,
            record: true,
            split: true,
            nee: true,
            kickstart: true,
            tree_digest: digest(1),
            estimate_digest: digest(2),
            fractions_digest: Vec::new(),
            spp_before: 60,
            tree_version: 3,
            fraction_version: 1,
            hold_records: true,
            records_epoch: 1_733_333_333_333,
        }),
        estimate: Some(v1::PixelEstimate {
            region: Some(v1::Rect {
                x0: 63,
                y0: 31,
                x1: 129,
                y1: 97,
            }),
            values: [0.5f32, 2.0].iter().flat_map(|x| x.to_le_bytes()).collect(),
        }),
    }
}

fn round_trip<M: Message + Default + PartialEq + std::fmt::Debug>(m: &M) {
    let bytes = m.encode_to_vec();
    assert!(!bytes.is_empty(), "{m:?} encodes to something");
    let back = M::decode(bytes.as_slice()).expect("decodes");
    assert_eq!(&back, m);
}

#[test]
fn control_messages_round_trip() {
    let offer = v1::CoordinatorMessage {
        msg: Some(coordinator_message::Msg::LeaseOffer(v1::LeaseOffer {
            lease: Some(sample_lease()),
        })),
    };
    round_trip(&offer);
    let back = v1::CoordinatorMessage::decode(offer.encode_to_vec().as_slice()).unwrap();
    let Some(coordinator_message::Msg::LeaseOffer(v1::LeaseOffer { lease: Some(l) })) = back.msg
    else {
        panic!("decoded as a lease offer: {back:?}");
    };
    let pass = l.pass.unwrap();
    assert_eq!(pass.kind(), v1::PassKind::Record);
    assert_eq!(pass.spp as u64 * pass.passes as u64, 16);
    assert_eq!(l.settings.unwrap().seed, Some(7));

    round_trip(&v1::CoordinatorMessage {
        msg: Some(coordinator_message::Msg::Registered(v1::Registered {
            worker_id: 3,
            heartbeat_interval_ms: 2_000,
            lease_timeout_ms: 10_000,
            protocol_version: PROTOCOL_VERSION,
            build_id: "pathfarm 0.1.0 abc123".into(),
            upload_key: vec![0xa5; 32],
        })),
    });
    // An empty message in a oneof still round-trips as that arm.
    let drain = v1::CoordinatorMessage {
        msg: Some(coordinator_message::Msg::Drain(v1::Drain::default())),
    };
    round_trip(&drain);
    round_trip(&v1::CoordinatorMessage {
        msg: Some(coordinator_message::Msg::FlushRecords(v1::FlushRecords {
            job_id: "job-4".into(),
            tree_digest: digest(1),
            records_epoch: 9,
        })),
    });
    round_trip(&v1::RecordsUpload {
        part: Some(v1::records_upload::Part::Header(v1::RecordsHeader {
            worker_id: 3,
            job_id: "job-4".into(),
            tree_digest: digest(1),
            records_epoch: 9,
            lost: false,
            size: 3,
            digest: digest(2),
            covered_leases: 4,
            covered_digest: digest(3),
        })),
    });
    round_trip(&v1::RecordsUpload {
        part: Some(v1::records_upload::Part::Data(vec![1, 2, 3])),
    });
    assert!(matches!(
        v1::CoordinatorMessage::decode(drain.encode_to_vec().as_slice())
            .unwrap()
            .msg,
        Some(coordinator_message::Msg::Drain(_))
    ));

    for msg in [
        worker_message::Msg::Register(v1::Register {
            protocol_version: PROTOCOL_VERSION,
            build_id: "pathfarm 0.1.0 abc123".into(),
            threads: 16,
            host_name: "render-07".into(),
            worker_name: "rack2".into(),
        }),
        worker_message::Msg::Heartbeat(v1::Heartbeat {
            active_lease_ids: vec![1, 2, u64::MAX],
        }),
        worker_message::Msg::RequestWork(v1::RequestWork { slots: 2 }),
        worker_message::Msg::LeaseFailed(v1::LeaseFailed {
            lease_id: 9,
            reason: "scene.xml: no such integrator".into(),
            fatal: true,
        }),
        worker_message::Msg::Draining(v1::Draining {}),
        worker_message::Msg::HandBack(v1::HandBack {
            lease_ids: vec![4, 5],
        }),
    ] {
        round_trip(&v1::WorkerMessage { msg: Some(msg) });
    }
}

#[test]
fn job_and_tile_messages_round_trip() {
    round_trip(&v1::JobStatus {
        job_id: "job-42".into(),
        name: "veach-ajar".into(),
        state: v1::JobState::FinalPass as i32,
        iteration: 6,
        tiles_done: 17,
        tiles_total: 60,
        samples_done: 123_456_789,
        samples_total: 640 * 360 * 1024,
        eta_seconds: Some(12.5),
        preview_available: true,
        failure_reason: String::new(),
        submitted_unix_ms: 1_767_225_600_000,
        finished_unix_ms: 0,
        spp_done: 508,
        priority: -3,
        unit: 9,
        pass_kind: v1::PassKind::Guided as i32,
        started_unix_ms: 1_767_225_601_000,
        nonfinite: 3,
        blocked_workers: vec!["render-07/gpu: lease 12: pixels: a sum is not finite".into()],
        batch: "shot-7".into(),
        iterations: vec![v1::IterationInfo {
            index: 2,
            spp: 4,
            variance: 3.5e-4,
            seconds: 1.25,
            tree_nodes: 41,
            tree_leaves: 21,
            training: true,
            rays_per_sample: 7.5,
        }],
        fell_back_after: Some(3),
    });
    round_trip(&v1::SubmitJobRequest {
        bundle: Some(v1::Bundle {
            root: "scene.xml".into(),
            files: vec![],
        }),
        settings: Some(v1::JobSettings {
            scene: None,
            budget: Some(job_settings::Budget::TimeSeconds(90.0)),
            tile_size: 32,
        }),
        priority: 10,
        name: "quick".into(),
        batch: "shot-7".into(),
    });
    round_trip(&v1::TileUpload {
        part: Some(tile_upload::Part::Header(v1::TileHeader {
            job_id: "job-42".into(),
            unit: 5,
            stats_size: 0,
            stats_digest: digest(10),
            tiles: vec![v1::UploadedTile {
                lease_id: 77,
                tile: Some(v1::Rect {
                    x0: 0,
                    y0: 0,
                    x1: 32,
                    y1: 32,
                }),
                counters: Some(v1::TileCounters {
                    rays: 1 << 33,
                    invalid_samples: 2,
                    split_paths: 300,
                    extra_light_samples: 40,
                    render_seconds: 1.25,
                    prepare_seconds: 0.5,
                    serialize_seconds: 0.0625,
                    nonfinite_records: 5,
                }),
                pixels_size: 32 * 32 * 16,
                pixels_digest: digest(9),
            }],
        })),
    });
    round_trip(&v1::TileAck {
        accepted: false,
        reject_reason: v1::TileRejectReason::Superseded as i32,
        detail: "tile accepted from lease 76".into(),
        duplicate: false,
    });
    // A full-size data part fits well inside gRPC's default 4 MiB message limit.
    let chunk = v1::DataChunk {
        part: Some(data_chunk::Part::Data(vec![0x5a; MAX_CHUNK_BYTES])),
    };
    round_trip(&chunk);
    assert!(chunk.encoded_len() < MAX_CHUNK_BYTES + 16);
}

/// The wire form is the contract: pin the bytes of small messages.
#[test]
fn wire_form_is_stable() {
    let rect = v1::Rect {
        x0: 1,
        y0: 2,
        x1: 3,
        y1: 300,
    };
    assert_eq!(
        rect.encode_to_vec(),
        [0x08, 1, 0x10, 2, 0x18, 3, 0x20, 0xac, 0x02]
    );
    let hb = v1::WorkerMessage {
        msg: Some(worker_message::Msg::Heartbeat(v1::Heartbeat {
            active_lease_ids: vec![1, 2],
        })),
    };
    // field 2 (heartbeat), length 4: field 1 packed, length 2: 1, 2.
    assert_eq!(hb.encode_to_vec(), [0x12, 4, 0x0a, 2, 1, 2]);
    assert_eq!(v1::JobState::Done as i32, 5);
    assert_eq!(v1::PassKind::Path as i32, 4);
    assert_eq!(v1::ResultKind::SdTree as i32, 3);
    assert_eq!(v1::TileRejectReason::Corrupt as i32, 4);
    assert_eq!(
        v1::JobState::from_str_name("JOB_STATE_FINAL_PASS"),
        Some(v1::JobState::FinalPass)
    );
}

#[test]
fn constants() {
    assert_eq!(PROTOCOL_VERSION, 6);
    assert_eq!(MAX_CHUNK_BYTES, 1_048_576);
}
