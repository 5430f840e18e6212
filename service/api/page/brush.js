// The λ brush's geometry: a stroke is the set of brush-sized squares along the pointer's path,
// in image pixels, as the rects PUT /jobs/{id}/lambda paints; drawn on a canvas over the
// preview until the server's λ layer shows them.

export class Stroke {
  constructor(size, value, image) {
    this.size = Math.max(1, Math.round(size));
    this.value = value;
    this.image = image;  // {w, h}
    this.keys = new Set();
    this.rects = [];
    this.last = null;
  }

  /** Add the squares from the previous point to this one, spaced so a fast drag leaves no gap. */
  to(point) {
    const from = this.last || point;
    const distance = Math.hypot(point.x - from.x, point.y - from.y);
    const steps = Math.max(1, Math.ceil(distance / Math.max(1, this.size / 2)));
    for (let i = 1; i <= steps; i++) {
      const t = i / steps;
      this.stamp(from.x + (point.x - from.x) * t, from.y + (point.y - from.y) * t);
    }
    this.last = point;
  }

  stamp(cx, cy) {
    const {w, h} = this.image;
    let x = Math.round(cx - this.size / 2);
    let y = Math.round(cy - this.size / 2);
    let width = this.size;
    let height = this.size;
    if (x < 0) { width += x; x = 0; }
    if (y < 0) { height += y; y = 0; }
    width = Math.min(width, w - x);
    height = Math.min(height, h - y);
    if (width < 1 || height < 1) return;  // off the image
    const key = `${x},${y},${width},${height}`;
    if (this.keys.has(key)) return;
    this.keys.add(key);
    this.rects.push({x, y, w: width, h: height, value: this.value});
  }
}

/** Translucent orange, stronger for a larger λ (the colour only hints; the λ layer is the truth). */
function strokeColour(value, low, high) {
  const t = Math.min(1, Math.max(0, (value - low) / (high - low || 1)));
  return `rgba(255, ${Math.round(180 - 130 * t)}, 0, ${0.25 + 0.5 * t})`;
}

export function drawStrokes(canvas, strokes, range) {
  const context = canvas.getContext("2d");
  context.clearRect(0, 0, canvas.width, canvas.height);
  for (const stroke of strokes) {
    context.fillStyle = strokeColour(stroke.value, range[0], range[1]);
    context.beginPath();  // one path per stroke: overlapping squares do not darken
    for (const r of stroke.rects) context.rect(r.x, r.y, r.w, r.h);
    context.fill();
  }
}
