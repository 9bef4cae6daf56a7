// Several calls in a burst (SSE events, clicks) -> one call of fn, ms after the first.
export function coalesced(fn, ms) {
  let timer = null;
  return () => {
    if (timer) return;
    timer = setTimeout(() => {
      timer = null;
      fn();
    }, ms);
  };
}
