"""Images without markers for the localizer: grey, noise, gradients, checkerboards, egg-crates,
   printed text, weaves and perforated plates (docs/experiments/localization-regular-patterns.md).

Usage: python scripts/regular_patterns.py OUT_DIR   (seeded: the same files every run)
"""
import os
import sys

import cv2
import numpy as np

out = sys.argv[1]; os.makedirs(out, exist_ok=True)
rng = np.random.default_rng(7)
def save(name, img): cv2.imwrite(os.path.join(out, name + ".png"), img)
sizes = [(640,480),(320,240),(427,320)]
for (w,h) in sizes:
    save(f"grey_{w}", np.full((h,w,3),128,np.uint8))
    save(f"noise_{w}", rng.integers(0,256,(h,w,3),dtype=np.uint8))
    n = rng.integers(0,256,(h,w,3)).astype(np.float32); b = cv2.GaussianBlur(n,(0,0),3); b = cv2.normalize(b,None,0,255,cv2.NORM_MINMAX)
    save(f"blurnoise_{w}", b.astype(np.uint8))
    x = np.linspace(0,1,w)[None,:]; y = np.linspace(0,1,h)[:,None]
    g = np.stack([255*x*np.ones_like(y), 255*y*np.ones_like(x), 255*(1-x)*np.ones_like(y)],-1)
    save(f"gradient_{w}", g.astype(np.uint8))
    for s in [8,12,16,20,24,30,40]:
        yy,xx = np.mgrid[0:h,0:w]
        c = (((xx//s)+(yy//s))%2)*255
        save(f"checker{s}_{w}", np.repeat(c[...,None].astype(np.uint8),3,-1))
# text
words = "the quick brown fox jumps over lazy dog sensor marker lattice gel pitch 0123456789 ABCDEFGHIJKLMNOPQRSTUVWXYZ".split()
fonts = [cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_PLAIN, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX, cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_SCRIPT_SIMPLEX]
for (w,h) in [(640,480),(1280,720)]:
  for scale in [0.4,0.6,1.0,1.5,2.5]:
    for inv in [0,1]:
        bg, fg = (245,240,235),(20,20,25)
        if inv: bg,fg = fg,bg
        img = np.full((h,w,3),bg,np.uint8)
        (tw,th),base = cv2.getTextSize("Ag", fonts[0], scale, 1)
        lh = int(th*1.9)+2; y = lh
        k=0
        while y < h:
            line = " ".join(rng.choice(words, 12))
            cv2.putText(img, line, (4, y), fonts[k%len(fonts)], scale, fg, max(1,int(scale*1.5)), cv2.LINE_AA)
            y += lh; k+=1
        save(f"text{scale}_{'inv' if inv else 'pos'}_{w}", img)
# weaves
for (w,h) in [(640,480)]:
  yy,xx = np.mgrid[0:h,0:w].astype(np.float32)
  for T in [6,10,16,24,36]:
    for ang in [0,20]:
      a = np.deg2rad(ang); u = xx*np.cos(a)+yy*np.sin(a); v = -xx*np.sin(a)+yy*np.cos(a)
      s = np.sin(2*np.pi*u/T)*np.sin(2*np.pi*v/T)
      save(f"eggcrate{T}_{ang}", np.repeat((128+100*s)[...,None],3,-1).clip(0,255).astype(np.uint8))
      for kind,(over,shift) in {"plain":(1,1),"twill":(2,1),"basket":(2,0)}.items():
        i = np.floor(u/T).astype(int); j = np.floor(v/T).astype(int)
        fu = (u/T)%1; fv=(v/T)%1
        if kind=="basket": warp = ((i//2 + j//2)%2==0)
        else: warp = (((i + shift*j)//over)%2==0)
        prof_warp = np.sin(np.pi*fu)**0.7   # thread across u
        prof_weft = np.sin(np.pi*fv)**0.7
        I = np.where(warp, 60+150*prof_warp*(0.8+0.2*np.sin(np.pi*fv)), 50+140*prof_weft*(0.8+0.2*np.sin(np.pi*fu)))
        col = np.stack([I*0.9, I*0.8, I*1.0],-1)
        save(f"{kind}{T}_{ang}", col.clip(0,255).astype(np.uint8))
# perforated plates
for (w,h) in [(640,480)]:
  for pitch in [10,16,24,40]:
    for ratio in [0.3,0.5,0.7,0.85]:
      for layout in ["sq","hex"]:
        for pol in ["dark","bright"]:
          plate, hole = ((200,200,205),(25,25,25)) if pol=="dark" else ((40,40,45),(235,235,235))
          img = np.full((h,w,3), plate, np.uint8)
          dy = pitch*np.sqrt(3)/2 if layout=="hex" else pitch
          r=0; y=3.3
          while y < h+pitch:
            x = 2.7 + (pitch/2 if layout=="hex" and r%2 else 0)
            while x < w+pitch:
              cv2.circle(img,(int(round(x*16)),int(round(y*16))),int(round(ratio*pitch/2*16)),hole,-1,cv2.LINE_AA,4); x+=pitch
            y+=dy; r+=1
          img = np.clip(img.astype(np.int16)+rng.integers(-2,3,img.shape),0,255).astype(np.uint8)
          save(f"perf{pitch}_{ratio}_{layout}_{pol}", img)
