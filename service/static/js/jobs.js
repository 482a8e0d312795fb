// Live job progress: one list item per job, fed by the job's server-sent events;
// falls back to polling GET /v1/jobs/{id} if the event stream breaks.
import { cancelJob, getJob, jobEventsUrl, jobResultUrl } from './api.js';

const TERMINAL = new Set(['succeeded', 'failed', 'canceled']);
// GET /v1/jobs/{id}/events sends `progress` ({state, progress, attempt}) while the job
// runs, then one last event named after the end state carrying the whole job.
const EVENT_NAMES = ['progress', 'succeeded', 'failed', 'canceled'];

/** Progress as a 0..1 fraction whether the server reports 0..1 or 0..100. */
export function fraction(progress) {
  const p = Number(progress) || 0;
  return Math.max(0, Math.min(1, p > 1 ? p / 100 : p));
}

/** A short label for a job, e.g. "bake sphere.obj (glb)" or "volume 64^3 (npy)". */
export function describe(job) {
  const p = job.params || {};
  if (job.kind === 'bake') return `bake ${p.filename || 'mesh'} (${p.format || 'glb'})`;
  if (job.kind === 'volume') return `volume ${p.resolution}^3 (${p.format})`;
  return `${job.kind || 'job'} ${job.id.slice(0, 8)}`;
}

export class JobList {
  /** @param {HTMLElement} list  the <ul> to fill */
  constructor(list) {
    this.list = list;
  }

  /**
   * List a job and follow it until it ends.
   * @param {object} job  a JobOut (the 202 body of a submission, or from GET /v1/jobs)
   * @param {{label?: string, onSuccess?: (job: object, resultUrl: string) => void,
   *          onView?: (resultUrl: string) => void}} options
   *   onView: offered as a "View in 3D" button on finished GLB bakes.
   */
  track(job, { label = describe(job), onSuccess = () => {}, onView = null } = {}) {
    const item = document.createElement('li');
    item.dataset.jobId = job.id;
    item.innerHTML = `<div><strong></strong> <span class="state">queued</span></div>
      <progress max="1" value="0"></progress>
      <div class="links"><button type="button" class="cancel">Cancel</button></div>`;
    item.querySelector('strong').textContent = label;
    item.querySelector('progress').setAttribute('aria-label', `Progress of ${label}`);
    const cancel = item.querySelector('.cancel');
    cancel.setAttribute('aria-label', `Cancel ${label}`);
    cancel.addEventListener('click', async () => {
      cancel.disabled = true;
      try { show(await cancelJob(job.id)); } catch { cancel.disabled = false; }
    });
    this.list.prepend(item);

    let finished = false;
    const show = (state) => {
      if (finished || !state) return;
      const status = state.state || state.status || 'running';
      item.dataset.state = status;
      item.querySelector('.state').textContent = status;
      item.querySelector('progress').value = status === 'succeeded' ? 1 : fraction(state.progress);
      if (!TERMINAL.has(status)) return;
      finished = true;
      cancel.remove();
      if (status === 'succeeded') {
        const url = jobResultUrl(job.id);
        const link = document.createElement('a');
        link.href = url;
        link.textContent = 'Download result';
        link.setAttribute('download', '');
        item.querySelector('.links').append(link);
        if (onView && job.kind === 'bake' && job.params?.format === 'glb') {
          const view = document.createElement('button');
          view.type = 'button';
          view.textContent = 'View in 3D';
          view.addEventListener('click', () => onView(url));
          item.querySelector('.links').append(' ', view);
        }
        onSuccess(state, url);
      } else {
        const error = state.error && (state.error.detail || state.error.message || state.error);
        item.querySelector('.state').classList.add('failed');
        item.querySelector('.state').textContent = `${status}${error ? `: ${error}` : ''}`;
      }
    };

    const poll = async () => {
      while (!finished) {
        try { show(await getJob(job.id)); } catch (e) { /* transient: retry */ }
        await new Promise((resolve) => setTimeout(resolve, 1000));
      }
    };

    if (TERMINAL.has(job.state)) {
      show(job);
      return;
    }
    const source = new EventSource(jobEventsUrl(job.id));
    const onEvent = (event) => {
      let data;
      try { data = JSON.parse(event.data); } catch { return; }
      show(data.job || data);
      if (finished) source.close();
    };
    source.onmessage = onEvent;
    for (const name of EVENT_NAMES) source.addEventListener(name, onEvent);
    source.onerror = () => {
      // The server closes the stream after the last event; EventSource would reconnect.
      source.close();
      if (!finished) poll();
    };
  }
}
