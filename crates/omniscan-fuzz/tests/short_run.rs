//! The short fuzz run CI makes: every reader on a few hundred mutated
//! inputs, with no panic, hang or broken promise (`scripts/fuzz` runs
//! them for as long as asked).

use std::time::Duration;

use omniscan_fuzz::{Target, fuzz};

#[test]
fn every_reader_survives_a_short_fuzz_run() {
    let work = tempfile::tempdir().unwrap();
    for target in Target::ALL {
        let report = fuzz(
            target,
            work.path(),
            Duration::from_secs(3),
            400,
            1,
            Duration::from_secs(20),
        )
        .unwrap();
        assert!(report.failures.is_empty(), "{report:#?}");
        assert!(report.executions > 20, "{report:#?}");
        // The mutations reach past the first check: more than one way to refuse.
        assert!(report.outcomes > 2, "{report:#?}");
    }
}
