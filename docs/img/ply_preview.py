# Draws docs/img/lego_mesh.png: a flat-shaded z-buffer rasteriser for the binary PLY mesh that
# `nerf export-mesh` writes (pure Python 3, no packages; ~10 s for 500 k triangles).
# Left: shaded by the vertex normals; right: the vertex colours, lit the same way.
# Usage: python3 ply_preview.py RUN/mesh.ply out.png
import struct, sys, zlib, math
path, out = sys.argv[1], sys.argv[2]
b = open(path,'rb').read()
h = b.index(b'end_header\n') + 11
hdr = b[:h].decode()
nv = int(hdr.split('element vertex ')[1].split('\n')[0]); nf = int(hdr.split('element face ')[1].split('\n')[0])
V = [struct.unpack_from('<6f3B', b, h + 27*i) for i in range(nv)]
F = [struct.unpack_from('<3i', b, h + 27*nv + 13*k + 1) for k in range(nf)]
W = 360
lo=[min(v[k] for v in V) for k in range(3)]; hi=[max(v[k] for v in V) for k in range(3)]
c=[(lo[k]+hi[k])/2 for k in range(3)]; s=max(hi[k]-lo[k] for k in range(3))*1.05
def view(az, el, colour):
    ca, sa, ce, se = math.cos(az), math.sin(az), math.cos(el), math.sin(el)
    def proj(p):
        x,y,z = p[0]-c[0], p[1]-c[1], p[2]-c[2]
        u = ca*x + sa*y; d = -sa*x + ca*y        # rotate about z
        v = ce*z - se*d; dd = se*z + ce*d        # tilt
        return ((u/s+0.5)*(W-1), (0.5-v/s)*(W-1), dd)
    P=[proj(v) for v in V]
    zb=[1e9]*(W*W); img=[255]*(3*W*W)
    light=(0.3,-0.5,0.8); ln=math.sqrt(sum(x*x for x in light)); light=[x/ln for x in light]
    for (i,j,k) in F:
        a,b_,cc=P[i],P[j],P[k]
        e1=(b_[0]-a[0],b_[1]-a[1],b_[2]-a[2]); e2=(cc[0]-a[0],cc[1]-a[1],cc[2]-a[2])
        area=e1[0]*e2[1]-e1[1]*e2[0]
        if area==0: continue
        x0=max(int(min(a[0],b_[0],cc[0])),0); x1=min(int(max(a[0],b_[0],cc[0]))+1,W-1)
        y0=max(int(min(a[1],b_[1],cc[1])),0); y1=min(int(max(a[1],b_[1],cc[1]))+1,W-1)
        n=[V[i][3]+V[j][3]+V[k][3],V[i][4]+V[j][4]+V[k][4],V[i][5]+V[j][5]+V[k][5]]
        nl=math.sqrt(sum(x*x for x in n)) or 1
        # normal in view space (same rotation)
        nx,ny,nz=[x/nl for x in n]; nu=ca*nx+sa*ny; nd=-sa*nx+ca*ny; nvv=ce*nz-se*nd; ndd=se*nz+ce*nd
        lam=0.25+0.75*max(0.0,-ndd*0.6+nvv*0.4+nu*0.3)
        if colour:
            col=[min(255,int((V[i][6+q]+V[j][6+q]+V[k][6+q])/3*(0.6+0.4*lam))) for q in range(3)]
        else:
            g=int(255*min(1,lam)); col=[g,g,g]
        for y in range(y0,y1+1):
            for x in range(x0,x1+1):
                px,py=x+0.5,y+0.5
                w1=((px-a[0])*e2[1]-(py-a[1])*e2[0])/area
                w2=(e1[0]*(py-a[1])-e1[1]*(px-a[0]))/area
                w0=1-w1-w2
                if w0<0 or w1<0 or w2<0: continue
                z=a[2]+w1*e1[2]+w2*e2[2]
                o=y*W+x
                if z<zb[o]:
                    zb[o]=z; img[3*o:3*o+3]=col
    return img
views=[view(math.radians(-30),math.radians(-25),False), view(math.radians(150),math.radians(-25),True)]
rows=[]
for y in range(W):
    rows.append(b'\x00'+bytes(views[0][3*y*W:3*(y+1)*W]+views[1][3*y*W:3*(y+1)*W]))
def chunk(t,d): return struct.pack('>I',len(d))+t+d+struct.pack('>I',zlib.crc32(t+d)&0xffffffff)
open(out,'wb').write(b'\x89PNG\r\n\x1a\n'+chunk(b'IHDR',struct.pack('>IIBBBBB',2*W,W,8,2,0,0,0))+chunk(b'IDAT',zlib.compress(b''.join(rows),9))+chunk(b'IEND',b''))
print(nv, nf)
