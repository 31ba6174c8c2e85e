// Rates from cumulative counts read now and then: a live session's poses, clouds and link bytes
// (its statuses), the bytes this page's socket received. Entry point: RateMeter.
//
// A rate is the count's change over a span of at least `minSpanMs`, so counts that come in
// bursts, twice within a few ms or not at all for a while (a status comes only when something
// changed) cannot swing it. Spans are smoothed exponentially by the time they cover (weight
// 1 - exp(-span / timeConstantMs)), so the figure does not depend on how irregular they are:
// after a source stops, the rate is its last value times exp(-elapsed / timeConstantMs).

export class RateMeter {
  /** `minSpanMs`: the shortest span a rate is taken over; `timeConstantMs`: the smoothing's. */
  constructor({ minSpanMs = 1000, timeConstantMs = 1500 } = {}) {
    this.minSpanMs = minSpanMs;
    this.timeConstantMs = timeConstantMs;
    this.reset();
  }

  /** Forgets the counts and the rate (the count is another session's now, or none). */
  reset() {
    this.start = null; // {count, atMs}: where the span being measured began
    this.perSecond = null; // the smoothed rate per second; null until a span was measured
  }

  /**
   * The count as it stood at `atMs` (milliseconds on a clock that never steps back, such as
   * performance.now()). A count lower than the last one starts over (the counter did: a
   * restarted server); one that is not a number is ignored.
   */
  add(count, atMs) {
    if (!Number.isFinite(count) || !Number.isFinite(atMs)) return;
    if (this.start === null || count < this.start.count) {
      this.reset();
      this.start = { count, atMs };
      return;
    }
    const spanMs = atMs - this.start.atMs;
    if (spanMs < this.minSpanMs) return;
    const current = ((count - this.start.count) * 1000) / spanMs;
    const weight = this.perSecond === null ? 1 : 1 - Math.exp(-spanMs / this.timeConstantMs);
    this.perSecond = this.perSecond === null ? current : this.perSecond + weight * (current - this.perSecond);
    this.start = { count, atMs };
  }
}
