//! Settings defaults written once: every settings struct derives
//! `clap::Args`, whose `default_value_t` attributes are the one place a
//! default is written, and its `Default` parses an empty command line.

/// The settings `T` with every field at its documented default: an empty
/// command line parsed by `T`'s own flags. Panics only if `T` has a
/// required field, which the settings' `defaults_parse` tests rule out.
pub fn defaults<T: clap::Args + clap::FromArgMatches>() -> T {
    let command = T::augment_args(clap::Command::new("defaults").no_binary_name(true));
    let matches = command
        .try_get_matches_from(std::iter::empty::<String>())
        .unwrap_or_else(|e| panic!("settings with a required field have no default: {e}"));
    T::from_arg_matches(&matches).unwrap_or_else(|e| panic!("settings defaults: {e}"))
}

/// `impl Default` by [`defaults`] for settings structs.
macro_rules! default_from_flags {
    ($($t:ty),* $(,)?) => {$(
        impl Default for $t {
            fn default() -> Self {
                $crate::settings::defaults()
            }
        }
    )*};
}
pub(crate) use default_from_flags;
