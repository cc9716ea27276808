// What the page's buttons and sliders send: MPEG-4 high-level ids and low-level FAPs (in FAPU).

export const EXPRESSIONS = [
  { id: 1, name: 'joy' }, { id: 2, name: 'sadness' }, { id: 3, name: 'anger' },
  { id: 4, name: 'fear' }, { id: 5, name: 'disgust' }, { id: 6, name: 'surprise' },
];

// MPEG-4 visemes 1-14 (0 = neutral).
export const VISEMES = [
  { id: 1, name: 'PP', title: 'p, b, m' }, { id: 2, name: 'FF', title: 'f, v' }, { id: 3, name: 'TH', title: 'th' },
  { id: 4, name: 'DD', title: 't, d' }, { id: 5, name: 'kk', title: 'k, g' }, { id: 6, name: 'CH', title: 'ch, j, sh' },
  { id: 7, name: 'SS', title: 's, z' }, { id: 8, name: 'nn', title: 'n, l' }, { id: 9, name: 'RR', title: 'r' },
  { id: 10, name: 'aa', title: 'car' }, { id: 11, name: 'E', title: 'bed' }, { id: 12, name: 'ih', title: 'tip' },
  { id: 13, name: 'oh', title: 'top' }, { id: 14, name: 'ou', title: 'book' },
];

// fap: one FAP, or several moved together by the same value.
export const SLIDERS = [
  { name: 'open jaw', fap: '3', min: 0, max: 900 },
  { name: 'lower lip down', fap: '5,10,11', min: -600, max: 200 },
  { name: 'smile (corners up)', fap: '12,13,59,60', min: -300, max: 400 },
  { name: 'stretch corners', fap: '6,7,53,54', min: -200, max: 400 },
  { name: 'brows up', fap: '31,32,33,34,35,36', min: -300, max: 500 },
  { name: 'blink', fap: '19,20', min: 0, max: 1024 },
  { name: 'head yaw', fap: '49', min: -15000, max: 15000 },
  { name: 'head pitch', fap: '48', min: -12000, max: 12000 },
  { name: 'look left/right', fap: '23,24', min: -20000, max: 20000 },
];
