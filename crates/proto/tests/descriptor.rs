//! The descriptor set: it decodes, holds both services with the expected rpcs, keeps the
//! field numbers of the contract's key messages, and documents every element.

use std::collections::BTreeMap;

use pathfarm_proto::{FILE_DESCRIPTOR_SET, JOBS_SERVICE, WORKERS_SERVICE};
use prost::Message;
use prost_types::{
    DescriptorProto, EnumDescriptorProto, FileDescriptorProto, FileDescriptorSet,
    ServiceDescriptorProto,
};

fn fds() -> FileDescriptorSet {
    FileDescriptorSet::decode(FILE_DESCRIPTOR_SET).expect("FILE_DESCRIPTOR_SET decodes")
}

fn files(fds: &FileDescriptorSet) -> Vec<&FileDescriptorProto> {
    fds.file
        .iter()
        .filter(|f| f.package() == "pathfarm.v1")
        .collect()
}

fn service<'a>(fds: &'a FileDescriptorSet, full_name: &str) -> &'a ServiceDescriptorProto {
    let name = full_name.strip_prefix("pathfarm.v1.").unwrap();
    let found: Vec<_> = files(fds)
        .into_iter()
        .flat_map(|f| &f.service)
        .filter(|s| s.name() == name)
        .collect();
    assert_eq!(found.len(), 1, "service {full_name} defined once");
    found[0]
}

fn message<'a>(fds: &'a FileDescriptorSet, name: &str) -> &'a DescriptorProto {
    files(fds)
        .into_iter()
        .flat_map(|f| &f.message_type)
        .find(|m| m.name() == name)
        .unwrap_or_else(|| panic!("message pathfarm.v1.{name} exists"))
}

/// (name, input type, output type, client streaming, server streaming) of each rpc.
fn methods(s: &ServiceDescriptorProto) -> Vec<(String, String, String, bool, bool)> {
    s.method
        .iter()
        .map(|m| {
            (
                m.name().to_string(),
                m.input_type().to_string(),
                m.output_type().to_string(),
                m.client_streaming(),
                m.server_streaming(),
            )
        })
        .collect()
}

fn expect(rows: &[(&str, &str, &str, bool, bool)]) -> Vec<(String, String, String, bool, bool)> {
    rows.iter()
        .map(|&(n, i, o, cs, ss)| {
            (
                n.to_string(),
                format!(".pathfarm.v1.{i}"),
                format!(".pathfarm.v1.{o}"),
                cs,
                ss,
            )
        })
        .collect()
}

#[test]
fn descriptor_set_holds_the_two_services_and_their_rpcs() {
    let fds = fds();
    let names: Vec<_> = files(&fds).iter().map(|f| f.name().to_string()).collect();
    assert_eq!(
        names,
        [
            "pathfarm/v1/common.proto",
            "pathfarm/v1/jobs.proto",
            "pathfarm/v1/workers.proto"
        ],
        "the package's files, dependencies first"
    );
    // Self-contained: reflection can serve every import.
    for f in &fds.file {
        for dep in &f.dependency {
            assert!(
                fds.file.iter().any(|g| g.name() == dep),
                "{} imports {dep}, which is not in the set",
                f.name()
            );
        }
    }
    let services: Vec<_> = files(&fds)
        .iter()
        .flat_map(|f| {
            f.service
                .iter()
                .map(|s| format!("pathfarm.v1.{}", s.name()))
        })
        .collect();
    assert_eq!(services, [JOBS_SERVICE, WORKERS_SERVICE]);

    assert_eq!(
        methods(service(&fds, JOBS_SERVICE)),
        expect(&[
            (
                "FindMissingBlobs",
                "FindMissingBlobsRequest",
                "FindMissingBlobsResponse",
                false,
                false
            ),
            ("UploadBlob", "BlobChunk", "UploadBlobResponse", true, false),
            (
                "SubmitJob",
                "SubmitJobRequest",
                "SubmitJobResponse",
                false,
                false
            ),
            ("WatchJob", "WatchJobRequest", "JobStatus", false, true),
            ("GetJob", "GetJobRequest", "GetJobResponse", false, false),
            (
                "ListJobs",
                "ListJobsRequest",
                "ListJobsResponse",
                false,
                false
            ),
            (
                "CancelJob",
                "CancelJobRequest",
                "CancelJobResponse",
                false,
                false
            ),
            (
                "SetJobPriority",
                "SetJobPriorityRequest",
                "SetJobPriorityResponse",
                false,
                false
            ),
            (
                "DownloadResult",
                "DownloadResultRequest",
                "DataChunk",
                false,
                true
            ),
            (
                "ListWorkers",
                "ListWorkersRequest",
                "ListWorkersResponse",
                false,
                false
            ),
        ])
    );
    assert_eq!(
        methods(service(&fds, WORKERS_SERVICE)),
        expect(&[
            ("Control", "WorkerMessage", "CoordinatorMessage", true, true),
            ("FetchBlob", "BlobRequest", "DataChunk", false, true),
            ("UploadTile", "TileUpload", "TileAck", true, false),
            ("UploadRecords", "RecordsUpload", "RecordsAck", true, false),
        ])
    );
}

fn field_numbers(m: &DescriptorProto) -> BTreeMap<String, i32> {
    m.field
        .iter()
        .map(|f| (f.name().to_string(), f.number()))
        .collect()
}

fn table(rows: &[(&str, i32)]) -> BTreeMap<String, i32> {
    rows.iter().map(|&(n, i)| (n.to_string(), i)).collect()
}

/// Field numbers are the wire contract: they are never renumbered. This pins the messages
/// the coordinator and the workers exchange most.
#[test]
fn key_messages_keep_their_field_numbers() {
    let fds = fds();
    assert_eq!(
        field_numbers(message(&fds, "PassSpec")),
        table(&[
            ("unit", 1),
            ("iteration", 2),
            ("kind", 3),
            ("first_sample", 4),
            ("spp", 5),
            ("passes", 6),
            ("guide", 7),
            ("record", 8),
            ("split", 9),
            ("nee", 10),
            ("kickstart", 11),
            ("tree_digest", 12),
            ("estimate_digest", 13),
            ("fractions_digest", 14),
            ("spp_before", 15),
            ("tree_version", 16),
            ("fraction_version", 17),
            ("hold_records", 18),
            ("records_epoch", 19),
        ])
    );
    assert_eq!(
        field_numbers(message(&fds, "RecordsHeader")),
        table(&[
            ("worker_id", 1),
            ("job_id", 2),
            ("tree_digest", 3),
            ("records_epoch", 4),
            ("lost", 5),
            ("size", 6),
            ("digest", 7),
            ("covered_leases", 8),
            ("covered_digest", 9),
        ])
    );
    assert_eq!(
        field_numbers(message(&fds, "Lease")),
        table(&[
            ("lease_id", 1),
            ("job_id", 2),
            ("deadline_unix_ms", 3),
            ("attempt", 4),
            ("tile", 5),
            ("bundle", 6),
            ("bundle_digest", 7),
            ("settings", 8),
            ("image", 9),
            ("pass", 10),
            ("estimate", 11),
        ])
    );
    assert_eq!(
        field_numbers(message(&fds, "WorkerMessage")),
        table(&[
            ("register", 1),
            ("heartbeat", 2),
            ("request_work", 3),
            ("lease_failed", 4),
            ("draining", 5),
            ("hand_back", 6),
        ])
    );
    assert_eq!(
        field_numbers(message(&fds, "CoordinatorMessage")),
        table(&[
            ("registered", 1),
            ("refused", 2),
            ("lease_offer", 3),
            ("cancel_lease", 4),
            ("drain", 5),
            ("prefetch", 6),
            ("flush_records", 7),
        ])
    );
    assert_eq!(
        field_numbers(message(&fds, "Register")),
        table(&[
            ("protocol_version", 1),
            ("build_id", 2),
            ("threads", 3),
            ("host_name", 4),
            ("worker_name", 5),
        ])
    );
    let job_state: Vec<_> = files(&fds)
        .into_iter()
        .flat_map(|f| &f.enum_type)
        .find(|e| e.name() == "JobState")
        .expect("enum JobState")
        .value
        .iter()
        .map(|v| (v.name().to_string(), v.number()))
        .collect();
    let want: Vec<_> = [
        "UNSPECIFIED",
        "QUEUED",
        "TRAINING",
        "FINAL_PASS",
        "ASSEMBLING",
        "DONE",
        "FAILED",
        "CANCELLED",
    ]
    .iter()
    .enumerate()
    .map(|(i, n)| (format!("JOB_STATE_{n}"), i as i32))
    .collect();
    assert_eq!(job_state, want);
}

/// The source path of element `i` of the repeated field numbered `field` in the element at
/// `path` (how descriptor.proto's source info addresses nested elements).
fn child(path: &[i32], field: i32, i: usize) -> Vec<i32> {
    let mut p = path.to_vec();
    p.extend([field, i as i32]);
    p
}

/// Walks a file's elements, noting each one without a leading comment.
struct Walker<'f> {
    /// The source paths that have a leading comment.
    documented: std::collections::HashSet<Vec<i32>>,
    file: &'f str,
    checked: usize,
    undocumented: Vec<String>,
}

impl Walker<'_> {
    fn check(&mut self, path: Vec<i32>, what: String) {
        self.checked += 1;
        if !self.documented.contains(&path) {
            self.undocumented.push(format!("{}: {what}", self.file));
        }
    }

    /// The element at `path` (`what name`) and its items (`item_what name.item`): an enum's
    /// values and a message's fields are both field 2 of their parent in descriptor.proto.
    fn element<'a>(
        &mut self,
        path: &[i32],
        what: &str,
        name: &str,
        item_what: &str,
        items: impl Iterator<Item = &'a str>,
    ) {
        self.check(path.to_vec(), format!("{what} {name}"));
        for (i, item) in items.enumerate() {
            self.check(child(path, 2, i), format!("{item_what} {name}.{item}"));
        }
    }

    fn enumeration(&mut self, e: &EnumDescriptorProto, path: Vec<i32>, scope: &str) {
        let values = e.value.iter().map(|v| v.name());
        self.element(
            &path,
            "enum",
            &format!("{scope}{}", e.name()),
            "enum value",
            values,
        );
    }

    fn message(&mut self, m: &DescriptorProto, path: Vec<i32>, scope: &str) {
        let name = format!("{scope}{}", m.name());
        self.element(
            &path,
            "message",
            &name,
            "field",
            m.field.iter().map(|f| f.name()),
        );
        for (i, nested) in m.nested_type.iter().enumerate() {
            self.message(nested, child(&path, 3, i), &format!("{name}."));
        }
        for (i, e) in m.enum_type.iter().enumerate() {
            self.enumeration(e, child(&path, 4, i), &format!("{name}."));
        }
    }

    fn file(&mut self, f: &FileDescriptorProto) {
        for (i, m) in f.message_type.iter().enumerate() {
            self.message(m, vec![4, i as i32], "");
        }
        for (i, e) in f.enum_type.iter().enumerate() {
            self.enumeration(e, vec![5, i as i32], "");
        }
        for (i, s) in f.service.iter().enumerate() {
            self.check(vec![6, i as i32], format!("service {}", s.name()));
            for (j, m) in s.method.iter().enumerate() {
                let path = child(&[6, i as i32], 2, j);
                self.check(path, format!("rpc {}.{}", s.name(), m.name()));
            }
        }
    }
}

/// Source paths (descriptor.proto field numbers) of every documented element of a file,
/// checked against its source info: every message, field, enum, enum value, service and
/// rpc must have a leading comment.
#[test]
fn every_element_is_documented() {
    let fds = fds();
    let mut undocumented = Vec::new();
    let mut checked = 0;
    for f in files(&fds) {
        let info = f
            .source_code_info
            .as_ref()
            .unwrap_or_else(|| panic!("{} has source info (comments)", f.name()));
        let documented = info
            .location
            .iter()
            .filter(|l| {
                l.leading_comments
                    .as_deref()
                    .is_some_and(|c| !c.trim().is_empty())
            })
            .map(|l| l.path.clone())
            .collect();
        let mut walker = Walker {
            documented,
            file: f.name(),
            checked: 0,
            undocumented: Vec::new(),
        };
        walker.file(f);
        checked += walker.checked;
        undocumented.extend(walker.undocumented);
    }
    assert!(checked > 200, "only {checked} elements checked");
    assert!(
        undocumented.is_empty(),
        "undocumented elements:\n{}",
        undocumented.join("\n")
    );
}
