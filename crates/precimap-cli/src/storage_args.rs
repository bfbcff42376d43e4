//! The settings of the storage life cycle: campaign size bounds (`serve`) and retention (every
//! process whose executors or reconciler clean up: `serve` and `work`).

use clap::Args;
use precimap_framework::{CampaignLimits, Retention};
use std::time::Duration;

/// Bounds on a submitted campaign, checked before anything is stored (422 above them).
#[derive(Args, Debug, Clone)]
pub struct LimitArgs {
    /// Most strips one campaign may have.
    #[arg(long, env = "PRECIMAP_MAX_STRIPS", default_value_t = CampaignLimits::default().max_strips)]
    pub max_strips: usize,
    /// Most trajectories one campaign may have.
    #[arg(long, env = "PRECIMAP_MAX_TRAJECTORIES", default_value_t = CampaignLimits::default().max_trajectories)]
    pub max_trajectories: usize,
    /// Most bytes of input objects (their distinct objects' sizes summed) one campaign may name.
    #[arg(long, env = "PRECIMAP_MAX_INPUT_BYTES", default_value_t = CampaignLimits::default().max_input_bytes)]
    pub max_input_bytes: u64,
}

impl LimitArgs {
    pub fn limits(&self) -> CampaignLimits {
        CampaignLimits {
            max_strips: self.max_strips,
            max_trajectories: self.max_trajectories,
            max_input_bytes: self.max_input_bytes,
        }
    }
}

/// How long stored objects are kept.
#[derive(Args, Debug, Clone)]
pub struct RetentionArgs {
    /// Seconds a finished campaign's work files (everything but its results) are kept after it
    /// finished; `never` keeps them (0: removed as it finishes).
    #[arg(long, env = "PRECIMAP_KEEP_WORK_S", default_value = "0")]
    pub keep_work_s: Seconds,
    /// Seconds after which a finished campaign is deleted with its results and the inputs it
    /// alone named; `never` keeps it until a client deletes it.
    #[arg(long, env = "PRECIMAP_KEEP_CAMPAIGNS_S", default_value = "never")]
    pub keep_campaigns_s: Seconds,
    /// Seconds an input no campaign names is kept after its upload; `never` keeps it until a
    /// client deletes it.
    #[arg(long, env = "PRECIMAP_KEEP_INPUTS_S", default_value = "never")]
    pub keep_inputs_s: Seconds,
    /// Seconds between sweeps of the object store for objects no campaign owns.
    #[arg(long, env = "PRECIMAP_STORE_SWEEP_S", default_value_t = 300)]
    pub store_sweep_s: u64,
}

impl RetentionArgs {
    pub fn retention(&self) -> Retention {
        Retention {
            work: self.keep_work_s.0,
            campaigns: self.keep_campaigns_s.0,
            inputs: self.keep_inputs_s.0,
            store_sweep_interval: Duration::from_secs(self.store_sweep_s),
        }
    }
}

/// A number of seconds, or `never`.
#[derive(Debug, Clone, Copy)]
pub struct Seconds(pub Option<Duration>);

impl std::str::FromStr for Seconds {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s.eq_ignore_ascii_case("never") {
            return Ok(Seconds(None));
        }
        s.parse::<u64>()
            .map(|n| Seconds(Some(Duration::from_secs(n))))
            .map_err(|_| format!("expected a number of seconds or `never`, got {s:?}"))
    }
}
