mod behaviour;
mod chi2;
mod mitsuba_values;
mod stats;
mod table;
