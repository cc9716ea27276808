// Microphone lip-sync: getUserMedia -> AudioWorklet -> 20 ms float32 PCM chunks -> the session's producer.

const WORKLET = `
class Chunker extends AudioWorkletProcessor {
  constructor(options) {
    super();
    this.size = options.processorOptions.size;
    this.buf = new Float32Array(this.size);
    this.n = 0;
  }
  process(inputs) {
    const ch = inputs[0] && inputs[0][0];
    if (!ch) return true;
    let i = 0;
    while (i < ch.length) {
      const take = Math.min(ch.length - i, this.size - this.n);
      this.buf.set(ch.subarray(i, i + take), this.n);
      this.n += take; i += take;
      if (this.n === this.size) { this.port.postMessage(this.buf.slice()); this.n = 0; }
    }
    return true;
  }
}
registerProcessor('facecast-chunker', Chunker);
`;

export class Microphone {
  constructor(producer, onInfo = () => {}) { this.producer = producer; this.onInfo = onInfo; }

  async start() {
    this.stream = await navigator.mediaDevices.getUserMedia({
      audio: { channelCount: 1, echoCancellation: false, noiseSuppression: false, autoGainControl: false } });
    this.ctx = new AudioContext();
    const rate = this.ctx.sampleRate;
    await this.producer.connect({ input: 'audio', rate, sample_format: 'f32' });
    const url = URL.createObjectURL(new Blob([WORKLET], { type: 'application/javascript' }));
    await this.ctx.audioWorklet.addModule(url);
    const src = this.ctx.createMediaStreamSource(this.stream);
    this.node = new AudioWorkletNode(this.ctx, 'facecast-chunker', { processorOptions: { size: Math.round(rate * 0.02) } });
    let chunks = 0;
    this.node.port.onmessage = (ev) => {
      this.producer.sendPcm(ev.data, rate);
      if (++chunks % 50 === 0) this.onInfo(`streaming ${rate} Hz audio: ${(chunks * 0.02).toFixed(0)} s sent`);
    };
    src.connect(this.node);
    this.onInfo(`microphone on (${rate} Hz); the face follows your voice`);
  }

  stop() {
    if (this.node) this.node.disconnect();
    if (this.stream) for (const t of this.stream.getTracks()) t.stop();
    if (this.ctx) this.ctx.close();
    this.producer.close();
    this.onInfo('microphone off');
  }
}
