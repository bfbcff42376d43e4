//! The system tests: simulated campaigns through the library, the `precimap` binary, the job
//! framework, the HTTP API and real services. One binary, so the stack is linked once.

mod calibration;
mod control;
mod end_to_end;
mod field;
mod framework;
mod hardening;
mod patterns;
