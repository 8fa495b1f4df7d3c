//! What kind of failure a stage's error is, for callers that act on it:
//! the command line's exit status, the Python exception's class, and the
//! distributed runner's decision to retry (a bad capture fails the same way
//! every time; a held lock or a full disk may not).

use omniscan_core::CoreError;

/// The kind of a stage's failure.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Failure {
    /// A file or setting the stage cannot use: retrying cannot help.
    Input,
    /// A file could not be read or written (missing, a permission, a full
    /// disk): may pass on another machine or later.
    File,
    /// Another process holds the output's lock.
    Busy,
    /// Anything else (a device lost, an internal error).
    Other,
}

impl Failure {
    /// The kind of `error`, by the type of the library error in its chain.
    pub fn of(error: &anyhow::Error) -> Failure {
        let core = |e: &CoreError| match e {
            CoreError::Io { .. } => Failure::File,
            CoreError::Busy { .. } => Failure::Busy,
            _ => Failure::Input,
        };
        for cause in error.chain() {
            if let Some(e) = cause.downcast_ref::<CoreError>() {
                return core(e);
            }
            if let Some(e) = cause.downcast_ref::<omniscan_splat::SplatError>() {
                return match e {
                    omniscan_splat::SplatError::Core(e) => core(e),
                    _ => Failure::Input,
                };
            }
            if let Some(e) = cause.downcast_ref::<omniscan_mesh::MeshError>() {
                return match e {
                    omniscan_mesh::MeshError::Io(e) => core(e),
                    omniscan_mesh::MeshError::File { .. } => Failure::File,
                    omniscan_mesh::MeshError::Input(_) => Failure::Input,
                };
            }
            if let Some(e) = cause.downcast_ref::<omniscan_ros::RosError>() {
                return match e {
                    omniscan_ros::RosError::Core(e) => core(e),
                    _ => Failure::Input,
                };
            }
            if cause
                .downcast_ref::<omniscan_register::RegisterError>()
                .is_some()
                || cause.downcast_ref::<serde_json::Error>().is_some()
            {
                return Failure::Input;
            }
            if cause.downcast_ref::<std::io::Error>().is_some() {
                return Failure::File;
            }
        }
        Failure::Other
    }

    /// The command line's exit status for it: 1 for input (and other)
    /// errors, sysexits' 74 (EX_IOERR) for a file that could not be read or
    /// written, 75 (EX_TEMPFAIL) for an output in use. Usage errors exit 2
    /// (clap's). `python -m omniscan.distributed` retries 74 and 75.
    pub fn exit_code(self) -> i32 {
        match self {
            Failure::Input | Failure::Other => 1,
            Failure::File => 74,
            Failure::Busy => 75,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn failures_are_told_apart_through_context() {
        let io = CoreError::io(
            "/x/model.ply",
            std::io::Error::from(std::io::ErrorKind::NotFound),
        );
        let busy = CoreError::Busy {
            path: "/x".into(),
            holder: "omniscan twin (process 1)".into(),
        };
        let input = omniscan_splat::SplatError::file(std::path::Path::new("/x"), "not a model");
        let wrapped = |e: anyhow::Error| e.context("reading model /x");
        assert_eq!(Failure::of(&wrapped(io.into())), Failure::File);
        assert_eq!(Failure::of(&wrapped(busy.into())), Failure::Busy);
        assert_eq!(Failure::of(&wrapped(input.into())), Failure::Input);
        assert_eq!(
            Failure::of(&anyhow::anyhow!("something else")),
            Failure::Other
        );
        assert_eq!(
            [Failure::Input, Failure::File, Failure::Busy].map(Failure::exit_code),
            [1, 74, 75]
        );
    }
}
