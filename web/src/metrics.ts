// What each bench metric means: the sentences of ``DEFINITIONS`` in
// server/servotune/bench/metrics.py, copied here because the server does not serve them (yet).
// Keep in step with that file; they are the hover text of the runs table's headers.

export const METRIC_DEFINITIONS: Record<string, string> = {
  step: "Commanded step y_final − y0 in units of y; its sign is the step direction used by the directional metrics.",
  band: "Settling band ± in units of y: the in-position window passed in, or 2 % of |step| when none is given (None for a zero step without a window).",
  samples: "Number of samples used: finite time and value, at or after the command time t0.",
  max_sample_gap_s: "Largest interval between consecutive samples from t0 (counted as the first point) to the last sample: every time metric is quantised to about this.",
  rise_time_s: "Time from the first 10 % crossing of the step to the first 90 % crossing after it, both in the step direction and located by linear interpolation between the two samples around them, with (t0, y0) as the first point (None for a zero step or when 90 % is never reached).",
  overshoot_pct: "Largest excursion of y beyond y_final in the step direction as a percentage of |step|, 0 when y never passes y_final (None for a zero step). The peak is the maximum, between the highest sample's neighbours, of the not-a-knot cubic spline through that sample and 3 samples either side at their own times; nearer the record's ends (or with a repeated time among them) the vertex of the parabola through it and its two neighbours when both are lower and the vertex lies between them (for two equal highest samples: the parabola symmetric about their midpoint through the outer neighbour giving the smaller rise); either raised above the highest sample by no more than the larger drop to a neighbour (a sampled peak is low by up to |y''| (gap/2)^2 / 2), else the highest sample (a plateau of three or more).",
  peak_time_s: "Time after t0 of the first sample furthest in the step direction (for a zero step: furthest from y_final).",
  peak_value: "Value of y at the sample of peak_time_s.",
  settling_time_s: "Time after which |y − y_final| ≤ band to the end of the record, linearly interpolated between the last point outside the band and the next sample (0 when no point from (t0, y0) on is outside; None when the last sample is outside the band or there is no band).",
  steady_state_error: "Mean of (y_final − y) over the samples in the last 10 % of the time from t0 to the last sample, at least the last 3 samples, signed and in units of y (None with fewer than 3 samples).",
  oscillations: "Number of sign changes of y − y_final with a hysteresis of ± band, starting from the side the response approaches from, i.e. the overshoot and undershoot half-cycles that leave the band (None for a zero step).",
  peak_following_error: "Largest |following error| over the samples from t0 on, missing values skipped (None without data).",
  rms_following_error: "Root mean square of the following error over the same samples, each sample weighted equally (None without data).",
  time_to_flag_s: "For the arrival flags inpos and in_target: time after t0 at which the flag rose, taken midway between the last read that showed it clear (from t0 on) and the first read that showed it set after that, None if it never drops and rises again. Flags are polled: the reads are the times the flags were read, not the times of the samples that carry them.",
  time_in_flag_s: "For every other flag (oc, stall, ...): total time it was set between t0 and its last read, each change taken midway between the read before it and the read that showed it (a spell shorter than the flag's poll period can fall between two reads and is not seen).",
  time_to_flag_resolution_s: "± of time_to_flag_s: half the time between the two reads the rise lies between (half the flag's poll period there).",
  time_in_flag_resolution_s: "± of time_in_flag_s: the sum of half the time between the two reads around each change counted.",
};

/** "None" in the server's sentences is "—" in the table. */
export function metricHelp(name: string): string {
  const text = METRIC_DEFINITIONS[name] ?? name;
  return text.replace(/\bNone\b/g, "—");
}
